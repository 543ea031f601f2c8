//! A pseudo-terminal pair for the emulators: the emulator keeps the master, clients open the
//! slave path (`/dev/pts/N`) exactly as they would open `/dev/ttyUSB0`.
//!
//! The slave is put in raw mode (no echo, no line editing, no CR/LF translation) because a
//! controller on a real serial line sees bytes, not a terminal. We do NOT keep the slave
//! open ourselves: on Linux a master whose slave has no open file reports `POLLHUP` and
//! `read` fails with `EIO`, which is how the emulator notices that the client closed the
//! port (and, later, that a new client opened it: the hang-up goes away).

use std::ffi::CStr;
use std::io;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd, RawFd};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The master side of a pty pair plus the slave's path.
#[derive(Debug)]
pub struct Pty {
    master: OwnedFd,
    slave_path: PathBuf,
}

/// What one [`Pty::read`] saw.
#[derive(Debug, PartialEq, Eq)]
pub enum ReadOutcome {
    /// Bytes from the client.
    Data(usize),
    /// Nothing arrived within the timeout; a client has the port open.
    Idle,
    /// No client has the slave open (never opened, or closed it).
    NoClient,
}

fn cvt(r: libc::c_int) -> io::Result<libc::c_int> {
    if r < 0 {
        Err(io::Error::last_os_error())
    } else {
        Ok(r)
    }
}

impl Pty {
    /// Open a new pty pair in raw mode. The master is non-blocking and close-on-exec.
    pub fn open() -> io::Result<Self> {
        // SAFETY: posix_openpt/grantpt/unlockpt/ptsname_r are called on a descriptor we own;
        // every return value is checked.
        unsafe {
            let fd = cvt(libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY | libc::O_CLOEXEC))?;
            let master = OwnedFd::from_raw_fd(fd);
            cvt(libc::grantpt(fd))?;
            cvt(libc::unlockpt(fd))?;
            let mut buf = [0 as libc::c_char; 128];
            let r = libc::ptsname_r(fd, buf.as_mut_ptr(), buf.len());
            if r != 0 {
                return Err(io::Error::from_raw_os_error(r));
            }
            let slave_path = PathBuf::from(CStr::from_ptr(buf.as_ptr()).to_string_lossy().into_owned());
            let pty = Pty { master, slave_path };
            pty.make_slave_raw()?;
            let flags = cvt(libc::fcntl(fd, libc::F_GETFL))?;
            cvt(libc::fcntl(fd, libc::F_SETFL, flags | libc::O_NONBLOCK))?;
            Ok(pty)
        }
    }

    /// Raw mode on the slave: the settings live with the tty, so they stay after we close
    /// our temporary slave descriptor (clients usually set their own anyway).
    fn make_slave_raw(&self) -> io::Result<()> {
        let c = std::ffi::CString::new(self.slave_path.as_os_str().as_encoded_bytes())
            .map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e))?;
        // SAFETY: open/tcgetattr/cfmakeraw/tcsetattr on a fresh descriptor, closed by OwnedFd.
        unsafe {
            let sfd = cvt(libc::open(c.as_ptr(), libc::O_RDWR | libc::O_NOCTTY | libc::O_CLOEXEC))?;
            let slave = OwnedFd::from_raw_fd(sfd);
            let mut t: libc::termios = std::mem::zeroed();
            cvt(libc::tcgetattr(slave.as_raw_fd(), &mut t))?;
            libc::cfmakeraw(&mut t);
            cvt(libc::tcsetattr(slave.as_raw_fd(), libc::TCSANOW, &t))?;
        }
        Ok(())
    }

    /// The path clients open (`/dev/pts/N`).
    pub fn slave_path(&self) -> &Path {
        &self.slave_path
    }

    fn raw(&self) -> RawFd {
        self.master.as_raw_fd()
    }

    /// Wait up to `timeout` for bytes from the client and read them into `buf`.
    pub fn read(&self, buf: &mut [u8], timeout: Duration) -> io::Result<ReadOutcome> {
        let mut pfd = libc::pollfd {
            fd: self.raw(),
            events: libc::POLLIN,
            revents: 0,
        };
        let ms = timeout.as_millis().min(i32::MAX as u128) as libc::c_int;
        // SAFETY: one valid pollfd.
        let n = unsafe { libc::poll(&mut pfd, 1, ms) };
        if n < 0 {
            let e = io::Error::last_os_error();
            return if e.kind() == io::ErrorKind::Interrupted {
                Ok(ReadOutcome::Idle)
            } else {
                Err(e)
            };
        }
        if n == 0 {
            return Ok(ReadOutcome::Idle);
        }
        if pfd.revents & libc::POLLIN != 0 {
            // SAFETY: buf is valid for buf.len() bytes.
            let r = unsafe { libc::read(self.raw(), buf.as_mut_ptr().cast(), buf.len()) };
            if r > 0 {
                return Ok(ReadOutcome::Data(r as usize));
            }
            let e = io::Error::last_os_error();
            return match e.raw_os_error() {
                Some(libc::EIO) => Ok(ReadOutcome::NoClient),
                Some(libc::EAGAIN) | Some(libc::EINTR) => Ok(ReadOutcome::Idle),
                _ if r == 0 => Ok(ReadOutcome::NoClient),
                _ => Err(e),
            };
        }
        if pfd.revents & (libc::POLLHUP | libc::POLLERR) != 0 {
            return Ok(ReadOutcome::NoClient);
        }
        Ok(ReadOutcome::Idle)
    }

    /// Write all of `bytes` to the client, waiting (bounded) while the pty buffer is full.
    /// Bytes for a client that is gone are discarded: `Ok(false)`.
    pub fn write_all(&self, mut bytes: &[u8]) -> io::Result<bool> {
        let deadline = std::time::Instant::now() + Duration::from_secs(2);
        while !bytes.is_empty() {
            // SAFETY: bytes is valid for bytes.len() bytes.
            let r = unsafe { libc::write(self.raw(), bytes.as_ptr().cast(), bytes.len()) };
            if r > 0 {
                bytes = &bytes[r as usize..];
                continue;
            }
            let e = io::Error::last_os_error();
            match e.raw_os_error() {
                Some(libc::EAGAIN) | Some(libc::EINTR) => {
                    if std::time::Instant::now() > deadline {
                        return Err(io::Error::new(
                            io::ErrorKind::TimedOut,
                            format!("{}: client does not read its replies", self.slave_path.display()),
                        ));
                    }
                    std::thread::sleep(Duration::from_millis(2));
                }
                Some(libc::EIO) => return Ok(false),
                _ => return Err(e),
            }
        }
        Ok(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{Read, Write};

    #[test]
    fn bytes_flow_both_ways_and_close_is_seen() {
        let pty = Pty::open().unwrap();
        let mut buf = [0u8; 64];
        assert_eq!(
            pty.read(&mut buf, Duration::from_millis(10)).unwrap(),
            ReadOutcome::NoClient
        );
        let mut client = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(pty.slave_path())
            .unwrap();
        client.write_all(b"/1 1 get pos\n").unwrap();
        let mut got = Vec::new();
        while got.len() < 13 {
            match pty.read(&mut buf, Duration::from_millis(500)).unwrap() {
                ReadOutcome::Data(n) => got.extend_from_slice(&buf[..n]),
                other => panic!("expected data, got {other:?}"),
            }
        }
        assert_eq!(got, b"/1 1 get pos\n", "raw mode must not translate or echo");
        assert!(pty.write_all(b"@01 1 OK IDLE -- 0\r\n").unwrap());
        let mut reply = [0u8; 20];
        client.read_exact(&mut reply).unwrap();
        assert_eq!(&reply, b"@01 1 OK IDLE -- 0\r\n");
        drop(client);
        assert_eq!(
            pty.read(&mut buf, Duration::from_millis(50)).unwrap(),
            ReadOutcome::NoClient
        );
    }
}
