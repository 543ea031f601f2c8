//! The rig file's `[camera] options` for `backend = "genicam"`: one typed reader, so the
//! rules and their messages live in one place and a typo is refused rather than silently
//! replaced by a default. Library-free: checked in every build.

use std::time::Duration;

use super::pixel::PixelFormat;
use crate::rig::{CameraSpec, OptionError};

/// How to open and drive one GenICam camera.
#[derive(Clone, Debug, PartialEq)]
pub struct GenicamOptions {
    /// Aravis device id (`Aravis-Fake-GV01`, `Basler-21234567`), or the camera's IP
    /// address for GigE Vision; None: the first camera Aravis finds (refused when more than
    /// one is present is left to the operator: name it in the rig file).
    pub device: Option<String>,
    /// Acceptable pixel formats in order of preference (empty: [`PixelFormat::PREFERENCE`]).
    pub pixel_formats: Vec<PixelFormat>,
    /// Longest wait for one frame after the software trigger before `capture` fails with a
    /// timeout (the capture policy then decides whether to try again).
    pub timeout: Duration,
    /// Stream buffers queued for the camera.
    pub buffers: u32,
    /// GigE Vision only: let Aravis receive the stream on a Linux packet socket (its fast
    /// path, default on). Off uses an ordinary UDP socket: needed where the packet socket
    /// sees nothing, e.g. a camera on the loopback interface (arv-fake-gv-camera in CI).
    pub packet_socket: bool,
    /// Raw `GainRaw` value meaning unity gain, for cameras without a `Gain` feature in dB.
    /// Without it only gain 1 is accepted on such a camera (set to the raw minimum).
    pub gain_unity_raw: Option<i64>,
}

impl Default for GenicamOptions {
    fn default() -> Self {
        GenicamOptions {
            device: None,
            pixel_formats: Vec::new(),
            timeout: Duration::from_secs(2),
            buffers: 4,
            packet_socket: true,
            gain_unity_raw: None,
        }
    }
}

/// The options this backend reads (for the unknown-key message).
pub const KEYS: &str = "device, pixel_formats, timeout_s, buffers, packet_socket, gain_unity_raw";

impl GenicamOptions {
    /// Read `camera.options`: `device` (string), `pixel_formats` (array of PFNC names,
    /// see [`PixelFormat::parse`]), `timeout_s` (0 < s < 3600), `buffers` (2 ..= 64),
    /// `packet_socket` (bool), `gain_unity_raw` (integer ≥ 1). The capture policy's keys
    /// and `overlap_readout` are read elsewhere and skipped here.
    pub fn from_rig(spec: &CameraSpec) -> Result<GenicamOptions, OptionError> {
        let mut opts = GenicamOptions::default();
        for (key, v) in &spec.options {
            let bad = |message: &str| OptionError {
                key: format!("camera.options.{key}"),
                value: v.to_string(),
                message: message.to_string(),
            };
            match key.as_str() {
                "device" => {
                    let s = v
                        .as_str()
                        .filter(|s| !s.trim().is_empty())
                        .ok_or_else(|| bad("must be an Aravis device id or an IP address (a non-empty string)"))?;
                    opts.device = Some(s.to_string());
                }
                "pixel_formats" => {
                    let list = v
                        .as_array()
                        .ok_or_else(|| bad("must be an array of pixel format names"))?;
                    opts.pixel_formats = list
                        .iter()
                        .map(|f| {
                            f.as_str().and_then(PixelFormat::parse).ok_or_else(|| OptionError {
                                key: format!("camera.options.{key}"),
                                value: f.to_string(),
                                message: "use Mono8, Mono16, RGB8, BayerRG8, BayerBG8, BayerGR8, BayerGB8 or their 16-bit forms (BayerRG16 …)".into(),
                            })
                        })
                        .collect::<Result<_, _>>()?;
                    if opts.pixel_formats.is_empty() {
                        return Err(bad("must name at least one format (or leave the option out)"));
                    }
                }
                "timeout_s" => {
                    let t = v
                        .as_float()
                        .or_else(|| v.as_integer().map(|i| i as f64))
                        .filter(|t| t.is_finite() && *t > 0.0 && *t < 3600.0)
                        .ok_or_else(|| bad("must be seconds in (0, 3600)"))?;
                    opts.timeout = Duration::from_secs_f64(t);
                }
                "buffers" => {
                    opts.buffers = v
                        .as_integer()
                        .filter(|n| (2..=64).contains(n))
                        .ok_or_else(|| bad("must be an integer in 2..=64"))? as u32;
                }
                "packet_socket" => {
                    opts.packet_socket = v.as_bool().ok_or_else(|| bad("must be true or false"))?;
                }
                "gain_unity_raw" => {
                    opts.gain_unity_raw = Some(
                        v.as_integer()
                            .filter(|n| *n >= 1)
                            .ok_or_else(|| bad("must be a positive integer"))?,
                    );
                }
                // The engine's capture policy (gonio `rig::capture`), validated there.
                "capture_timeout_s" | "capture_retries" | "saturation" | "saturation_fraction" => {}
                // Validated by `CameraSpec::readout_overlaps_motion` (refused when true).
                "overlap_readout" => {}
                _ => return Err(bad(&format!("unknown option of the genicam camera (known: {KEYS})"))),
            }
        }
        Ok(opts)
    }

    /// The formats to try, in order.
    pub fn formats(&self) -> Vec<PixelFormat> {
        if self.pixel_formats.is_empty() {
            PixelFormat::PREFERENCE.to_vec()
        } else {
            self.pixel_formats.clone()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::genicam::pixel::Cfa;

    fn spec(opts: &str) -> CameraSpec {
        toml::from_str(&format!(
            "backend = \"genicam\"\nwidth = 512\nheight = 512\nfocal_length_px = 500.0\nbit_depth = 8\nexposure_s = 0.01\noptions = {{ {opts} }}"
        ))
        .unwrap()
    }

    #[test]
    fn options_parse_with_defaults() {
        let o = GenicamOptions::from_rig(&spec("")).unwrap();
        assert_eq!(o, GenicamOptions::default());
        assert_eq!(o.formats().len(), PixelFormat::PREFERENCE.len());
        let o = GenicamOptions::from_rig(&spec(
            "device = \"127.0.0.1\", pixel_formats = [\"BayerGR8\", \"Mono16\"], timeout_s = 1.5, buffers = 8, packet_socket = false, gain_unity_raw = 16, capture_retries = 2",
        ))
        .unwrap();
        assert_eq!(o.device.as_deref(), Some("127.0.0.1"));
        assert_eq!(o.formats(), vec![PixelFormat::Bayer(Cfa::Grbg, 8), PixelFormat::Mono16]);
        assert_eq!(
            (o.timeout, o.buffers, o.packet_socket, o.gain_unity_raw),
            (Duration::from_millis(1500), 8, false, Some(16))
        );
    }

    #[test]
    fn bad_options_name_the_key_and_the_fix() {
        for (bad, key, hint) in [
            ("devcie = \"x\"", "camera.options.devcie", "known: device"),
            ("device = \"\"", "camera.options.device", "IP address"),
            (
                "pixel_formats = [\"BayerRG12p\"]",
                "camera.options.pixel_formats",
                "BayerRG8",
            ),
            ("pixel_formats = []", "camera.options.pixel_formats", "at least one"),
            ("timeout_s = 0", "camera.options.timeout_s", "(0, 3600)"),
            ("buffers = 1", "camera.options.buffers", "2..=64"),
            (
                "packet_socket = \"no\"",
                "camera.options.packet_socket",
                "true or false",
            ),
            ("gain_unity_raw = 0", "camera.options.gain_unity_raw", "positive"),
        ] {
            let e = GenicamOptions::from_rig(&spec(bad)).unwrap_err();
            assert_eq!(e.key, key, "{bad}");
            assert!(e.to_string().contains(hint), "{bad}: {e}");
        }
    }
}
