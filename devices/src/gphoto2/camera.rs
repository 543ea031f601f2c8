//! The libgphoto2 [`Camera`]: find, configure (shutter speed, aperture, ISO from the
//! camera's choices, read back), capture (capture, download, delete from the card,
//! decode, linearise).
//!
//! libgphoto2 is blocking (the `gphoto2` crate runs it on its own thread); the async trait
//! methods wait on tokio's blocking pool, one camera behind one mutex, and every wait has
//! a deadline ([`super::wait_until`]): a call that does not answer in time is cancelled
//! and ends in a `Timeout` naming the camera, so a hung camera never hangs a run.

use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use async_trait::async_trait;
use gphoto2::widget::{RadioWidget, TextWidget};

use super::options::Gphoto2Options;
use super::{
    classify, device_error, file_kind, nearest_shutter, parse_shutter, pick_choice, srgb_to_linear16, wait_until,
    Deadline, FileKind, APERTURE_KEYS, ISO_KEYS, SHUTTER_KEY,
};
use crate::camera::{Camera, CameraConfig, FoundCamera, Frame, FrameMeta};
use crate::rig::CameraSpec;
use crate::DeviceError;

/// A still camera implementing [`Camera`].
pub struct Gphoto2Camera {
    name: String,
    inner: Arc<Mutex<Inner>>,
}

/// What the last `configure` applied (read back from the camera).
#[derive(Clone, Debug)]
struct Applied {
    config: CameraConfig,
    /// The shutter-speed choice as the camera wrote it back (checked before each capture).
    shutter: String,
}

struct Inner {
    name: String,
    opts: Gphoto2Options,
    context: gphoto2::Context,
    camera: gphoto2::Camera,
    /// libgphoto2's model name and port of the opened camera.
    model: String,
    port: String,
    applied: Option<Applied>,
    sequence: u64,
    /// Folder and name of the last captured file on the card.
    last_file: Option<(String, String)>,
}

/// The typed error of a failed libgphoto2 call.
fn gp_err(device: &str, command: &str, e: &gphoto2::Error) -> DeviceError {
    device_error(device, command, classify(&format!("{:?}", e.kind())), &e.to_string())
}

/// Wait for a libgphoto2 task (the crate's worker thread) until `deadline`: its answer, or
/// a `Timeout` naming the camera and the call, after asking libgphoto2 to cancel it.
fn wait<T: 'static + Send>(
    device: &str,
    command: &str,
    task: gphoto2::task::Task<gphoto2::Result<T>>,
    deadline: Deadline,
) -> Result<T, DeviceError> {
    let mut task = task;
    match wait_until(device, command, &mut task, deadline) {
        Ok(answer) => answer.map_err(|e| gp_err(device, command, &e)),
        Err(timeout) => {
            task.cancel();
            tracing::warn!(
                camera = device,
                command,
                limit_s = deadline.limit().as_secs_f64(),
                "libgphoto2 call did not answer in time; cancelled"
            );
            Err(timeout)
        }
    }
}

/// The still cameras libgphoto2 detects (what `gphoto2 --auto-detect` prints), for `gonio
/// devices list`: each with the rig-file options that open exactly it. `timeout` bounds
/// the detection.
pub fn list_cameras(timeout: Duration) -> Result<Vec<FoundCamera>, DeviceError> {
    let name = "gphoto2";
    let context = gphoto2::Context::new().map_err(|e| gp_err(name, "gp_context_new", &e))?;
    let found = wait(name, "auto-detect", context.list_cameras(), Deadline::after(timeout))?;
    Ok(found
        .map(|d| FoundCamera {
            backend: "gphoto2".into(),
            rig_options: format!("port = \"{}\", model = \"{}\"", d.port, d.model),
            model: d.model,
            address: d.port,
        })
        .collect())
}

pub use crate::camera::FromRigError;

impl Gphoto2Camera {
    /// Open the camera the options name: by port and/or model, or the only one found.
    pub fn open(opts: Gphoto2Options) -> Result<Gphoto2Camera, DeviceError> {
        let wanted = match (&opts.model, &opts.port) {
            (Some(m), Some(p)) => format!("{m} on {p}"),
            (Some(m), None) => m.clone(),
            (None, Some(p)) => p.clone(),
            (None, None) => "(the one found)".into(),
        };
        let name = format!("gphoto2 {wanted}");
        let context = gphoto2::Context::new().map_err(|e| gp_err(&name, "gp_context_new", &e))?;
        let limit = opts.timeout;
        let found: Vec<gphoto2::list::CameraDescriptor> =
            wait(&name, "auto-detect", context.list_cameras(), Deadline::after(limit))?.collect();
        let listed = || {
            if found.is_empty() {
                "none".to_string()
            } else {
                found
                    .iter()
                    .map(|d| format!("{} on {}", d.model, d.port))
                    .collect::<Vec<_>>()
                    .join("; ")
            }
        };
        let matching: Vec<_> = found
            .iter()
            .filter(|d| opts.port.as_ref().is_none_or(|p| &d.port == p))
            .filter(|d| opts.model.as_ref().is_none_or(|m| &d.model == m))
            .collect();
        let desc = match matching.as_slice() {
            [one] => (*one).clone(),
            [] => {
                return Err(DeviceError::Disconnected {
                    device: name,
                    command: "auto-detect".into(),
                    reason: format!(
                        "no camera matches (found: {}); is it on and connected by USB, and are \
                         camera.options.port/model right?",
                        listed()
                    ),
                })
            }
            _ => {
                return Err(DeviceError::Rejected {
                    device: name,
                    command: "auto-detect".into(),
                    reason: format!(
                        "more than one camera matches ({}); name one with camera.options.port or camera.options.model",
                        listed()
                    ),
                })
            }
        };
        let camera = wait(&name, "open", context.get_camera(&desc), Deadline::after(limit))?;
        let name = format!("gphoto2 {} on {}", desc.model, desc.port);
        tracing::info!(camera = %name, "opened libgphoto2 camera");
        Ok(Gphoto2Camera {
            name: name.clone(),
            inner: Arc::new(Mutex::new(Inner {
                name,
                opts,
                context,
                camera,
                model: desc.model,
                port: desc.port,
                applied: None,
                sequence: 0,
                last_file: None,
            })),
        })
    }

    /// Open the camera a rig file's `[camera]` table describes (`backend = "gphoto2"`).
    pub fn from_rig(spec: &CameraSpec) -> Result<Gphoto2Camera, FromRigError> {
        let opts = Gphoto2Options::from_rig(spec)?;
        Ok(Gphoto2Camera::open(opts)?)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// libgphoto2's model name and port of the opened camera.
    pub fn model_and_port(&self) -> (String, String) {
        let inner = self.lock();
        (inner.model.clone(), inner.port.clone())
    }

    /// The camera's choices of a radio setting (`shutterspeed`, `f-number`, `iso`) and its
    /// current value.
    pub fn choices(&self, key: &str) -> Result<(Vec<String>, String), DeviceError> {
        let inner = self.lock();
        let w = inner.radio(key, inner.deadline())?;
        Ok((w.choices_iter().collect(), w.choice()))
    }

    /// Folder and name of the last captured file on the card.
    pub fn last_file(&self) -> Option<(String, String)> {
        self.lock().last_file.clone()
    }

    /// The names of the files in a folder of the card (to check a deletion).
    pub fn files_in(&self, folder: &str) -> Result<Vec<String>, DeviceError> {
        let inner = self.lock();
        Ok(wait(
            &inner.name,
            &format!("list {folder}"),
            inner.camera.fs().list_files(folder),
            inner.deadline(),
        )?
        .collect())
    }

    /// Configure without an async runtime (tests, examples).
    pub fn configure_blocking(&self, config: &CameraConfig) -> Result<CameraConfig, DeviceError> {
        self.lock().configure(config)
    }

    /// Capture without an async runtime.
    pub fn capture_blocking(&self) -> Result<Frame, DeviceError> {
        self.lock().capture()
    }
}

impl Inner {
    fn rejected(&self, command: &str, reason: String) -> DeviceError {
        DeviceError::Rejected {
            device: self.name.clone(),
            command: command.to_string(),
            reason,
        }
    }

    /// A deadline of `timeout_s` from now, for one call outside a capture.
    fn deadline(&self) -> Deadline {
        Deadline::after(self.opts.timeout)
    }

    fn radio(&self, key: &str, deadline: Deadline) -> Result<RadioWidget, DeviceError> {
        wait(
            &self.name,
            &format!("{key} (read)"),
            self.camera.config_key::<RadioWidget>(key),
            deadline,
        )
    }

    /// The first of `keys` the camera has, as a radio widget, or None when it has none of
    /// them. Only "no such setting" (libgphoto2's bad-parameters or not-supported answer)
    /// moves on to the next key: a camera that stopped answering is its own error, not a
    /// missing setting.
    fn first_radio(&self, keys: &[&'static str]) -> Result<Option<(&'static str, RadioWidget)>, DeviceError> {
        for key in keys {
            match wait(
                &self.name,
                &format!("{key} (read)"),
                self.camera.config_key::<RadioWidget>(key),
                self.deadline(),
            ) {
                Ok(w) => return Ok(Some((key, w))),
                Err(DeviceError::Rejected { .. }) => continue,
                Err(e) => return Err(e),
            }
        }
        Ok(None)
    }

    /// Set `widget` (the camera's `key`) to its choice `index` and return the choice the
    /// camera reports afterwards.
    fn set_radio(&self, key: &str, widget: RadioWidget, choice: &str) -> Result<String, DeviceError> {
        let command = format!("{key}={choice}");
        widget
            .set_choice(choice)
            .map_err(|e| gp_err(&self.name, &command, &e))?;
        wait(&self.name, &command, self.camera.set_config(&widget), self.deadline())?;
        Ok(self.radio(key, self.deadline())?.choice())
    }

    /// A setting the rig file asks for (aperture, ISO): chosen from the camera's choices,
    /// set, and read back.
    fn apply_choice(&self, what: &str, keys: &[&'static str], wanted: &str) -> Result<String, DeviceError> {
        let Some((key, widget)) = self.first_radio(keys)? else {
            return Err(self.rejected(
                what,
                format!(
                    "camera.options.{what} = \"{wanted}\", but the camera has no {what} setting ({}); \
                     remove the option (a manual lens has no aperture setting; some cameras expose no ISO)",
                    keys.join(", ")
                ),
            ));
        };
        let choices: Vec<String> = widget.choices_iter().collect();
        let index = pick_choice(what, &choices, wanted).map_err(|reason| self.rejected(key, reason))?;
        let choice = choices[index].clone();
        let back = self.set_radio(key, widget, &choice)?;
        if back != choice {
            return Err(self.rejected(
                key,
                format!("set \"{choice}\" but the camera reads back \"{back}\" (is the mode dial on M?)"),
            ));
        }
        Ok(back)
    }

    fn configure(&mut self, config: &CameraConfig) -> Result<CameraConfig, DeviceError> {
        self.applied = None;
        if (config.gain - 1.0).abs() > 1e-9 {
            return Err(self.rejected(
                "gain",
                format!(
                    "gain {}: a still camera's gain is its ISO speed; set the rig file's camera gain to 1 and \
                     camera.options.iso to the ISO wanted",
                    config.gain
                ),
            ));
        }
        if let Some(a) = self.opts.aperture.clone() {
            let got = self.apply_choice("aperture", &APERTURE_KEYS, &a)?;
            tracing::info!(camera = %self.name, aperture = %got, "aperture set");
        }
        if let Some(iso) = self.opts.iso.clone() {
            let got = self.apply_choice("iso", &ISO_KEYS, &iso)?;
            tracing::info!(camera = %self.name, iso = %got, "ISO set");
        }
        let widget = self.radio(SHUTTER_KEY, self.deadline())?;
        let choices: Vec<String> = widget.choices_iter().collect();
        let (index, _) =
            nearest_shutter(&choices, config.exposure).map_err(|reason| self.rejected(SHUTTER_KEY, reason))?;
        let choice = choices[index].clone();
        let back = self.set_radio(SHUTTER_KEY, widget, &choice)?;
        if back != choice {
            return Err(self.rejected(
                SHUTTER_KEY,
                format!("set \"{choice}\" but the camera reads back \"{back}\" (set the mode dial to M)"),
            ));
        }
        let exposure = parse_shutter(&back).map_err(|reason| self.rejected(SHUTTER_KEY, reason))?;
        if (exposure / config.exposure - 1.0).abs() > 1e-6 {
            tracing::warn!(camera = %self.name, asked_s = config.exposure, applied_s = exposure, choice = %back,
                "exposure is the camera's nearest shutter speed, not the one asked");
        }
        let applied = CameraConfig {
            exposure,
            gain: 1.0,
            bit_depth: 16,
            ..config.clone()
        };
        tracing::info!(camera = %self.name, shutter = %back, exposure, "camera configured");
        self.applied = Some(Applied {
            config: applied.clone(),
            shutter: back,
        });
        Ok(applied)
    }

    fn capture(&mut self) -> Result<Frame, DeviceError> {
        let Some(applied) = self.applied.clone() else {
            return Err(self.rejected("capture", "camera not configured (call configure first)".into()));
        };
        // One deadline for the whole capture (the shutter check, capture, download, delete):
        // `timeout_s` beyond the exposure. A camera that stops answering ends the capture
        // in a `Timeout`, which the capture policy retries and then reports.
        let deadline = Deadline::after(self.opts.timeout + Duration::from_secs_f64(applied.config.exposure.max(0.0)));
        // The shutter speed is read again now: one changed on the camera's dial must not
        // give a frame with the wrong exposure.
        let now = self.radio(SHUTTER_KEY, deadline)?.choice();
        if now != applied.shutter {
            return Err(self.rejected(
                SHUTTER_KEY,
                format!(
                    "shutter speed changed during the run: \"{now}\" read back, \"{}\" configured (the dial or \
                     another program?); no frame taken",
                    applied.shutter
                ),
            ));
        }
        let timestamp = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        let path = wait(&self.name, "capture", self.camera.capture_image(), deadline)?;
        let (folder, file) = (path.folder().to_string(), path.name().to_string());
        self.last_file = Some((folder.clone(), file.clone()));
        let command = format!("download {folder}/{file}");
        let cf = wait(
            &self.name,
            &command,
            self.camera.fs().download(&folder, &file),
            deadline,
        )?;
        let data = wait(&self.name, &command, cf.get_data(&self.context), deadline)?;
        if !self.opts.keep_on_card {
            let command = format!("delete {folder}/{file}");
            wait(
                &self.name,
                &command,
                self.camera.fs().delete_file(&folder, &file),
                deadline,
            )?;
        }
        let (width, height) = (applied.config.width, applied.config.height);
        let rgb = match file_kind(&file, &data) {
            FileKind::Jpeg => decode_jpeg(&data).map_err(|reply| DeviceError::Garbled {
                device: self.name.clone(),
                command: format!("decode {file}"),
                reply,
            })?,
            FileKind::Raw => {
                return Err(self.rejected(
                    "capture",
                    format!(
                        "{file} is a raw file, which this backend does not decode yet; set the camera's image \
                         quality to JPEG (only)"
                    ),
                ))
            }
            FileKind::Other => {
                return Err(self.rejected(
                    "capture",
                    format!("{file} ({} bytes) is neither a JPEG nor a raw file", data.len()),
                ))
            }
        };
        if (rgb.0, rgb.1) != (width, height) {
            return Err(self.rejected(
                "capture",
                format!(
                    "{file} is {} × {} but the rig file's camera is {width} × {height}; set camera.width and \
                     camera.height to the camera's image size (or its image size setting to match)",
                    rgb.0, rgb.1
                ),
            ));
        }
        self.sequence += 1;
        Ok(Frame {
            width,
            height,
            data: rgb.2.into_iter().map(srgb_to_linear16).collect(),
            meta: FrameMeta {
                timestamp,
                exposure: applied.config.exposure,
                gain: 1.0,
                sequence: self.sequence,
                bit_depth: 16,
            },
        })
    }

    /// A text setting, or None when the camera lacks it (or does not answer in time).
    fn text(&self, key: &str) -> Option<String> {
        wait(
            &self.name,
            key,
            self.camera.config_key::<TextWidget>(key),
            self.deadline(),
        )
        .ok()
        .map(|w| w.value().trim().to_string())
        .filter(|v| !v.is_empty())
    }
}

/// A JPEG's width, height and 8-bit RGB values (sRGB, as stored).
pub fn decode_jpeg(data: &[u8]) -> Result<(usize, usize, Vec<u8>), String> {
    use zune_jpeg::zune_core::bytestream::ZCursor;
    use zune_jpeg::zune_core::colorspace::ColorSpace;
    use zune_jpeg::zune_core::options::DecoderOptions;
    // Up to a 100-megapixel sensor's JPEG.
    let options = DecoderOptions::default()
        .jpeg_set_out_colorspace(ColorSpace::RGB)
        .set_max_width(16_384)
        .set_max_height(16_384);
    let mut dec = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(data), options);
    let rgb = dec.decode().map_err(|e| format!("not a decodable JPEG: {e:?}"))?;
    let info = dec.info().ok_or("JPEG without an image header")?;
    let (w, h) = (info.width as usize, info.height as usize);
    if rgb.len() < w * h * 3 {
        return Err(format!("JPEG of {w} × {h} decoded to only {} values", rgb.len()));
    }
    Ok((w, h, rgb[..w * h * 3].to_vec()))
}

#[async_trait]
impl Camera for Gphoto2Camera {
    fn name(&self) -> &str {
        &self.name
    }

    async fn configure(&self, config: &CameraConfig) -> Result<CameraConfig, DeviceError> {
        let config = config.clone();
        crate::camera::blocking_call(&self.name, "configure", &self.inner, move |inner| {
            inner.configure(&config)
        })
        .await
    }

    async fn capture(&self) -> Result<Frame, DeviceError> {
        crate::camera::blocking_call(&self.name, "capture", &self.inner, |inner| inner.capture()).await
    }

    /// libgphoto2's model name, then manufacturer, model, serial number and firmware as
    /// the camera reports them (`manufacturer`, `cameramodel`, `serialnumber`,
    /// `deviceversion`); the ones it lacks are left out.
    async fn identity(&self) -> Result<String, DeviceError> {
        let inner = self.inner.clone();
        let name = self.name.clone();
        tokio::task::spawn_blocking(move || {
            let inner = inner.lock().unwrap_or_else(|p| p.into_inner());
            let mut parts = vec![inner.model.clone()];
            let maker_model: Vec<String> = ["manufacturer", "cameramodel"]
                .iter()
                .filter_map(|k| inner.text(k))
                .collect();
            if !maker_model.is_empty() {
                parts.push(maker_model.join(" "));
            }
            if let Some(sn) = inner.text("serialnumber") {
                parts.push(format!("S/N {sn}"));
            }
            if let Some(fw) = inner.text("deviceversion") {
                parts.push(format!("firmware {fw}"));
            }
            parts.join(", ")
        })
        .await
        .map_err(|e| DeviceError::Other {
            device: name,
            command: "identity".into(),
            reason: format!("worker task failed: {e}"),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The error-kind names [`classify`] matches are the `gphoto2` crate's own.
    #[test]
    fn classify_knows_the_crates_error_kinds() {
        use super::super::ErrorKind as E;
        use gphoto2::error::ErrorKind as K;
        for (kind, want) in [
            (K::IoUsbFind, E::Disconnected),
            (K::IoUsbClaim, E::Disconnected),
            (K::UnknownPort, E::Disconnected),
            (K::CameraBusy, E::Transient),
            (K::Timeout, E::Transient),
            (K::BadParameters, E::Rejected),
            (K::NotSupported, E::Rejected),
            (K::FileNotFound, E::Rejected),
            (K::Other, E::Other),
        ] {
            assert_eq!(classify(&format!("{kind:?}")), want, "{kind:?}");
        }
    }

    #[test]
    fn a_broken_jpeg_is_an_error_not_a_panic() {
        assert!(decode_jpeg(&[0xFF, 0xD8, 0xFF, 0xE0, 0, 16]).is_err());
        assert!(decode_jpeg(&[]).is_err());
    }
}
