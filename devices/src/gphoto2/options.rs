//! The rig file's `[camera] options` for `backend = "gphoto2"`: one typed reader, so a
//! typo is refused rather than silently replaced by a default. Library-free: checked in
//! every build.

use crate::rig::{CameraSpec, OptionError};
use std::time::Duration;

/// How to find and set up one still camera.
#[derive(Clone, Debug, PartialEq)]
pub struct Gphoto2Options {
    /// libgphoto2 port (`usb:001,004`, as `gphoto2 --auto-detect` lists it); None: any.
    pub port: Option<String>,
    /// Model as libgphoto2 names it (`Nikon DSC D750`); None: any. With neither, the one
    /// camera found is used, and more than one is refused (a run must not pick a camera
    /// by USB enumeration order).
    pub model: Option<String>,
    /// Aperture to set, matched against the camera's choices (`8`, `f/8`); None: leave the
    /// lens as it is (its value is logged).
    pub aperture: Option<String>,
    /// ISO speed to set, matched against the camera's choices (`100`); None: leave it.
    pub iso: Option<String>,
    /// Keep each captured file on the card after the download (default false: deleted,
    /// so a long run does not fill the card and the card never holds a stale file).
    pub keep_on_card: bool,
    /// Longest wait for one libgphoto2 call (open, a setting); a capture (capture,
    /// download, delete together) gets this plus its exposure (`timeout_s`, default 20 s).
    /// Past it the call is cancelled and the result is a `Timeout` naming the camera.
    pub timeout: Duration,
}

impl Default for Gphoto2Options {
    fn default() -> Gphoto2Options {
        Gphoto2Options {
            port: None,
            model: None,
            aperture: None,
            iso: None,
            keep_on_card: false,
            timeout: Duration::from_secs(20),
        }
    }
}

/// The options this backend reads (for the unknown-key message).
pub const KEYS: &str = "port, model, aperture, iso, keep_on_card, timeout_s";

impl Gphoto2Options {
    /// Read `camera.options`: `port`, `model`, `aperture` (string or number), `iso`
    /// (string or integer), `keep_on_card` (bool). The capture policy's keys and
    /// `overlap_readout` are read elsewhere and skipped here.
    pub fn from_rig(spec: &CameraSpec) -> Result<Gphoto2Options, OptionError> {
        let mut opts = Gphoto2Options::default();
        for (key, v) in &spec.options {
            let bad = |message: &str| OptionError {
                key: format!("camera.options.{key}"),
                value: v.to_string(),
                message: message.to_string(),
            };
            let text = || -> Option<String> {
                match v {
                    toml::Value::String(s) if !s.trim().is_empty() => Some(s.trim().to_string()),
                    toml::Value::Integer(i) => Some(i.to_string()),
                    toml::Value::Float(f) if f.is_finite() => Some(f.to_string()),
                    _ => None,
                }
            };
            match key.as_str() {
                "port" => {
                    let s = v.as_str().filter(|s| s.contains(':')).ok_or_else(|| {
                        bad("must be a libgphoto2 port such as \"usb:001,004\" (gphoto2 --auto-detect lists them)")
                    })?;
                    opts.port = Some(s.to_string());
                }
                "model" => {
                    let s = v
                        .as_str()
                        .filter(|s| !s.trim().is_empty())
                        .ok_or_else(|| bad("must be the camera model as libgphoto2 names it (a non-empty string)"))?;
                    opts.model = Some(s.to_string());
                }
                "aperture" => {
                    opts.aperture = Some(text().ok_or_else(|| bad("must be an f-number such as 8 or \"f/8\""))?);
                }
                "iso" => {
                    opts.iso = Some(text().ok_or_else(|| bad("must be an ISO speed such as 100"))?);
                }
                "keep_on_card" => {
                    opts.keep_on_card = v.as_bool().ok_or_else(|| bad("must be true or false"))?;
                }
                "timeout_s" => {
                    let t = v
                        .as_float()
                        .or_else(|| v.as_integer().map(|i| i as f64))
                        .filter(|t| t.is_finite() && *t > 0.0 && *t < 3600.0)
                        .ok_or_else(|| bad("must be seconds in (0, 3600), e.g. 20"))?;
                    opts.timeout = Duration::from_secs_f64(t);
                }
                // The engine's capture policy (gonio `rig::capture`), validated there.
                "capture_timeout_s" | "capture_retries" | "saturation" | "saturation_fraction" => {}
                // Validated by `CameraSpec::readout_overlaps_motion` (refused when true).
                "overlap_readout" => {}
                _ => return Err(bad(&format!("unknown option of the gphoto2 camera (known: {KEYS})"))),
            }
        }
        Ok(opts)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(opts: &str) -> CameraSpec {
        toml::from_str(&format!(
            "backend = \"gphoto2\"\nwidth = 6016\nheight = 4016\nfocal_length_px = 8000.0\nbit_depth = 16\nexposure_s = 0.01\noptions = {{ {opts} }}"
        ))
        .unwrap()
    }

    #[test]
    fn options_parse_with_defaults() {
        assert_eq!(Gphoto2Options::from_rig(&spec("")).unwrap(), Gphoto2Options::default());
        let o = Gphoto2Options::from_rig(&spec(
            "port = \"usb:001,001\", model = \"Nikon DSC D750\", aperture = 8, iso = 100, keep_on_card = true, capture_retries = 2, timeout_s = 5",
        ))
        .unwrap();
        assert_eq!(o.timeout, Duration::from_secs(5));
        assert_eq!(Gphoto2Options::default().timeout, Duration::from_secs(20));
        assert_eq!(o.port.as_deref(), Some("usb:001,001"));
        assert_eq!(o.model.as_deref(), Some("Nikon DSC D750"));
        assert_eq!(
            (o.aperture.as_deref(), o.iso.as_deref(), o.keep_on_card),
            (Some("8"), Some("100"), true)
        );
        let o = Gphoto2Options::from_rig(&spec("aperture = 5.6, iso = \"Auto\"")).unwrap();
        assert_eq!((o.aperture.as_deref(), o.iso.as_deref()), (Some("5.6"), Some("Auto")));
    }

    #[test]
    fn bad_options_name_the_key_and_the_fix() {
        for (bad, key, hint) in [
            ("prot = \"usb:\"", "camera.options.prot", "known: port"),
            ("port = \"001,004\"", "camera.options.port", "usb:001,004"),
            ("model = \"\"", "camera.options.model", "non-empty"),
            ("aperture = true", "camera.options.aperture", "f/8"),
            ("iso = \"\"", "camera.options.iso", "ISO speed"),
            ("keep_on_card = 1", "camera.options.keep_on_card", "true or false"),
            ("timeout_s = 0", "camera.options.timeout_s", "(0, 3600)"),
            ("timeout_s = \"long\"", "camera.options.timeout_s", "(0, 3600)"),
        ] {
            let e = Gphoto2Options::from_rig(&spec(bad)).unwrap_err();
            assert_eq!(e.key, key, "{bad}");
            assert!(e.to_string().contains(hint), "{bad}: {e}");
        }
    }
}
