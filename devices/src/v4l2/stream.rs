//! Memory-mapped V4L2 capture streaming with a poll timeout.
//!
//! The `v4l` crate's own `MmapStream` panics in `Drop` when `VIDIOC_STREAMOFF` fails and
//! re-queues a buffer it still owns after a timed-out dequeue; a measurement rig must
//! survive stalls and unplugged cameras, so the queue bookkeeping lives here: every buffer
//! dequeued is copied out (converted) and queued again before the next dequeue, a timeout
//! leaves the queue untouched, and teardown never panics. The ioctls themselves go through
//! `v4l::v4l2` and its bindings.

use std::io;
use std::os::raw::c_void;
use std::time::Duration;

use v4l::v4l2;
use v4l::v4l_sys::{v4l2_buffer, v4l2_requestbuffers};

const BUF_TYPE_VIDEO_CAPTURE: u32 = 1;
const MEMORY_MMAP: u32 = 1;
/// `V4L2_BUF_FLAG_ERROR`: the buffer was returned but its data is corrupt.
pub const BUF_FLAG_ERROR: u32 = 0x40;
pub const BUF_FLAG_TIMESTAMP_MASK: u32 = 0xe000;
pub const BUF_FLAG_TIMESTAMP_MONOTONIC: u32 = 0x2000;
pub const BUF_FLAG_TSTAMP_SRC_MASK: u32 = 0x70000;
pub const BUF_FLAG_TSTAMP_SRC_SOE: u32 = 0x10000;

/// Which ioctl (or system call) failed, for the typed device error.
#[derive(Debug)]
pub struct StreamError {
    pub command: &'static str,
    pub source: io::Error,
}

impl StreamError {
    fn new(command: &'static str, source: io::Error) -> Self {
        StreamError { command, source }
    }
}

/// Metadata of a dequeued buffer.
#[derive(Clone, Copy, Debug)]
pub struct BufferMeta {
    pub index: usize,
    pub bytesused: usize,
    pub flags: u32,
    pub sequence: u32,
    /// Driver timestamp in seconds (CLOCK_MONOTONIC when the flags say so).
    pub timestamp: f64,
}

/// Outcome of waiting for a buffer.
pub enum Dequeued {
    Buffer(BufferMeta),
    /// Nothing arrived within the timeout.
    TimedOut,
}

struct Mapping {
    ptr: *mut c_void,
    len: usize,
}

/// An mmap capture stream on an open device file descriptor.
pub struct MmapStream {
    fd: i32,
    maps: Vec<Mapping>,
    streaming: bool,
}

// SAFETY: the mappings are plain shared memory owned by this value; nothing else aliases
// them mutably, and all access goes through `&mut self` / `&self` under the camera's mutex.
unsafe impl Send for MmapStream {}

fn zeroed_buffer(index: u32) -> v4l2_buffer {
    // SAFETY: v4l2_buffer is a plain C struct for which all-zero is a valid value.
    let mut b: v4l2_buffer = unsafe { std::mem::zeroed() };
    b.type_ = BUF_TYPE_VIDEO_CAPTURE;
    b.memory = MEMORY_MMAP;
    b.index = index;
    b
}

impl MmapStream {
    /// Request `count` driver buffers (the driver may grant a different number), map them,
    /// queue them all and start streaming.
    pub fn start(fd: i32, count: u32) -> Result<MmapStream, StreamError> {
        // SAFETY: all-zero is valid for this C struct.
        let mut req: v4l2_requestbuffers = unsafe { std::mem::zeroed() };
        req.count = count;
        req.type_ = BUF_TYPE_VIDEO_CAPTURE;
        req.memory = MEMORY_MMAP;
        // SAFETY: the pointer is to a live, correctly typed struct for this ioctl.
        unsafe { v4l2::ioctl(fd, v4l2::vidioc::VIDIOC_REQBUFS, &mut req as *mut _ as *mut c_void) }
            .map_err(|e| StreamError::new("VIDIOC_REQBUFS", e))?;
        if req.count == 0 {
            return Err(StreamError::new(
                "VIDIOC_REQBUFS",
                io::Error::new(io::ErrorKind::OutOfMemory, "driver granted no buffers"),
            ));
        }
        let mut stream = MmapStream {
            fd,
            maps: Vec::with_capacity(req.count as usize),
            streaming: false,
        };
        for index in 0..req.count {
            let mut buf = zeroed_buffer(index);
            // SAFETY: as above.
            unsafe { v4l2::ioctl(fd, v4l2::vidioc::VIDIOC_QUERYBUF, &mut buf as *mut _ as *mut c_void) }
                .map_err(|e| StreamError::new("VIDIOC_QUERYBUF", e))?;
            let len = buf.length as usize;
            // SAFETY: mapping the driver buffer at the offset the driver returned; unmapped
            // in `Drop`.
            let offset = unsafe { buf.m.offset } as libc::off_t;
            let ptr = unsafe {
                v4l2::mmap(
                    std::ptr::null_mut(),
                    len,
                    libc::PROT_READ | libc::PROT_WRITE,
                    libc::MAP_SHARED,
                    fd,
                    offset,
                )
            }
            .map_err(|e| StreamError::new("mmap", e))?;
            stream.maps.push(Mapping { ptr, len });
        }
        for index in 0..stream.maps.len() {
            stream.queue(index)?;
        }
        let mut typ = BUF_TYPE_VIDEO_CAPTURE as i32;
        // SAFETY: VIDIOC_STREAMON takes a pointer to the buffer type.
        unsafe { v4l2::ioctl(fd, v4l2::vidioc::VIDIOC_STREAMON, &mut typ as *mut _ as *mut c_void) }
            .map_err(|e| StreamError::new("VIDIOC_STREAMON", e))?;
        stream.streaming = true;
        Ok(stream)
    }

    pub fn buffer_count(&self) -> usize {
        self.maps.len()
    }

    /// Give a buffer back to the driver.
    pub fn queue(&mut self, index: usize) -> Result<(), StreamError> {
        let mut buf = zeroed_buffer(index as u32);
        // SAFETY: as above.
        unsafe { v4l2::ioctl(self.fd, v4l2::vidioc::VIDIOC_QBUF, &mut buf as *mut _ as *mut c_void) }
            .map_err(|e| StreamError::new("VIDIOC_QBUF", e))
    }

    /// Wait up to `timeout` for a filled buffer and dequeue it. The caller must `queue` it
    /// again once its data has been copied.
    pub fn dequeue(&mut self, timeout: Duration) -> Result<Dequeued, StreamError> {
        let mut pfd = libc::pollfd {
            fd: self.fd,
            events: libc::POLLIN,
            revents: 0,
        };
        let ms = timeout.as_millis().min(i32::MAX as u128) as i32;
        // SAFETY: one valid pollfd.
        let n = unsafe { libc::poll(&mut pfd, 1, ms) };
        if n < 0 {
            let e = io::Error::last_os_error();
            if e.kind() == io::ErrorKind::Interrupted {
                return Ok(Dequeued::TimedOut);
            }
            return Err(StreamError::new("poll", e));
        }
        if n == 0 {
            return Ok(Dequeued::TimedOut);
        }
        if pfd.revents & (libc::POLLERR | libc::POLLHUP | libc::POLLNVAL) != 0 && pfd.revents & libc::POLLIN == 0 {
            // A vb2 queue reports POLLERR when it is not streaming or the device is gone;
            // DQBUF below says which (ENODEV/EPIPE/EINVAL), so fall through to it.
            tracing::debug!(revents = pfd.revents, "poll reported an error condition");
        }
        let mut buf = zeroed_buffer(0);
        // SAFETY: as above.
        let r = unsafe { v4l2::ioctl(self.fd, v4l2::vidioc::VIDIOC_DQBUF, &mut buf as *mut _ as *mut c_void) };
        match r {
            Ok(()) => {}
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => return Ok(Dequeued::TimedOut),
            Err(e) => return Err(StreamError::new("VIDIOC_DQBUF", e)),
        }
        let index = buf.index as usize;
        if index >= self.maps.len() {
            return Err(StreamError::new(
                "VIDIOC_DQBUF",
                io::Error::new(
                    io::ErrorKind::InvalidData,
                    format!("driver returned buffer index {index}"),
                ),
            ));
        }
        Ok(Dequeued::Buffer(BufferMeta {
            index,
            bytesused: (buf.bytesused as usize).min(self.maps[index].len),
            flags: buf.flags,
            sequence: buf.sequence,
            timestamp: buf.timestamp.tv_sec as f64 + buf.timestamp.tv_usec as f64 * 1e-6,
        }))
    }

    /// The data of a dequeued buffer (up to `bytesused`).
    pub fn data(&self, meta: &BufferMeta) -> &[u8] {
        let m = &self.maps[meta.index];
        // SAFETY: the mapping is live for the lifetime of `self` and `bytesused` was clamped
        // to its length; the driver does not write a buffer while it is dequeued.
        unsafe { std::slice::from_raw_parts(m.ptr as *const u8, meta.bytesused.min(m.len)) }
    }

    /// Stop streaming and release the buffers. Errors are logged, never raised: this runs
    /// on teardown paths (including a vanished device) where nothing better can be done.
    pub fn stop(&mut self) {
        if self.streaming {
            let mut typ = BUF_TYPE_VIDEO_CAPTURE as i32;
            // SAFETY: as above.
            if let Err(e) = unsafe {
                v4l2::ioctl(
                    self.fd,
                    v4l2::vidioc::VIDIOC_STREAMOFF,
                    &mut typ as *mut _ as *mut c_void,
                )
            } {
                tracing::debug!(error = %e, "VIDIOC_STREAMOFF failed during teardown");
            }
            self.streaming = false;
        }
        for m in self.maps.drain(..) {
            // SAFETY: unmapping exactly what `start` mapped.
            if let Err(e) = unsafe { v4l2::munmap(m.ptr, m.len) } {
                tracing::debug!(error = %e, "munmap failed during teardown");
            }
        }
        // SAFETY: all-zero is valid for this C struct; count 0 frees the driver buffers.
        let mut req: v4l2_requestbuffers = unsafe { std::mem::zeroed() };
        req.type_ = BUF_TYPE_VIDEO_CAPTURE;
        req.memory = MEMORY_MMAP;
        if let Err(e) = unsafe { v4l2::ioctl(self.fd, v4l2::vidioc::VIDIOC_REQBUFS, &mut req as *mut _ as *mut c_void) }
        {
            tracing::debug!(error = %e, "VIDIOC_REQBUFS(0) failed during teardown");
        }
    }
}

impl Drop for MmapStream {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Now on CLOCK_MONOTONIC, the clock V4L2 drivers stamp buffers with.
pub fn monotonic_now() -> f64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: valid out pointer; CLOCK_MONOTONIC always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}
