//! What the simulator knows that a real rig does not ([`GroundTruth`]).
//!
//! Every truth a check compares against comes through this trait: the exact rectified
//! image, the radiance before the sensor, and the simulated sensor, lens and mechanics that
//! calibrations are checked against. Code outside `rig/` never reads the simulator's rig
//! file keys itself, so those keys have one reader (the simulator) and one door (this file).

use gonio_devices::image::RgbImage;
use gonio_simulator::SimWorld;

/// The simulator's mechanical error model of one axis (re-exported: the mechanical
/// calibration checks its estimates against it).
pub use gonio_simulator::mechanics::MechanicalErrors;
/// The simulator's non-linear response and colour crosstalk (re-exported: the radiometric
/// calibration checks its curve against it).
pub use gonio_simulator::sensor::SensorResponse;

/// The simulated sensor's numbers, as the simulator uses them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SensorTruth {
    pub full_well_e: f64,
    pub read_noise_e: f64,
    pub dark_current_e_s: f64,
    /// Electrons per (W m⁻² sr⁻¹ · s) at a pixel.
    pub sensitivity_e_per_radiance_s: f64,
    /// Relative fall-off at the image corners: `1 − v · r²/r_corner²`.
    pub vignetting: f64,
}

impl SensorTruth {
    /// The radiometric constant `K` of an ideal linear sensor: normalised signal per
    /// (radiance · exposure · gain), the scale of the ground truth.
    pub fn k(&self) -> f64 {
        self.sensitivity_e_per_radiance_s / self.full_well_e.max(1.0)
    }
}

/// What the simulator knows that a real rig does not: the exact rectified image, and the
/// radiance the camera sees before its sensor.
pub trait GroundTruth: Send + Sync {
    /// Ground truth for axis configuration `q` (radians) in the units of the rectified
    /// images (normalised sensor signal, not clipped).
    fn truth(&self, q: &[f64], width: usize, height: usize) -> RgbImage;
    /// The same, normalised at `exposure_s` and `gain` rather than the camera's current
    /// setting (HDR brackets change it while truths of earlier measurements are rendered).
    fn truth_at(&self, q: &[f64], width: usize, height: usize, _exposure_s: f64, _gain: f64) -> RgbImage {
        self.truth(q, width, height)
    }
    /// The camera's radiance image (W m⁻² sr⁻¹) at configuration `q`, no sensor effects.
    fn radiance(&self, q: &[f64]) -> RgbImage;
    /// The homing offsets (degrees) the simulator's mechanical error model drew for axis
    /// `index` so far, oldest first: the truth that mechanical calibration's homing
    /// repeatability is checked against. Empty without a model.
    fn home_offsets_deg(&self, _index: usize) -> Vec<f64> {
        Vec::new()
    }
    /// The simulated sensor's numbers (`None`: no simulated sensor).
    fn sensor(&self) -> Option<SensorTruth> {
        None
    }
    /// The simulated sensor's response curve and crosstalk; `None` for the linear,
    /// colour-clean default sensor.
    fn sensor_response(&self) -> Option<SensorResponse> {
        None
    }
    /// The simulated lens' distortion (OpenCV order k1, k2, p1, p2, k3; zero = pinhole).
    fn distortion(&self) -> [f64; 5] {
        [0.0; 5]
    }
    /// The mechanical error model of axis `index` (`None`: an ideal axis).
    fn mechanical_errors(&self, _index: usize) -> Option<MechanicalErrors> {
        None
    }
}

impl GroundTruth for SimWorld {
    fn truth(&self, q: &[f64], width: usize, height: usize) -> RgbImage {
        SimWorld::truth(self, q, width, height)
    }
    fn truth_at(&self, q: &[f64], width: usize, height: usize, exposure_s: f64, gain: f64) -> RgbImage {
        SimWorld::truth_at(self, q, width, height, exposure_s, gain)
    }
    fn radiance(&self, q: &[f64]) -> RgbImage {
        self.raw_radiance(q)
    }
    fn home_offsets_deg(&self, index: usize) -> Vec<f64> {
        self.axes.get(index).map(|a| a.home_offsets_deg()).unwrap_or_default()
    }
    fn sensor(&self) -> Option<SensorTruth> {
        let s = self.sensor.lock().expect("sensor poisoned");
        Some(SensorTruth {
            full_well_e: s.full_well_e,
            read_noise_e: s.read_noise_e,
            dark_current_e_s: s.dark_current_e_s,
            sensitivity_e_per_radiance_s: s.sensitivity_e_per_radiance_s,
            vignetting: s.vignetting,
        })
    }
    fn sensor_response(&self) -> Option<SensorResponse> {
        self.response.clone()
    }
    fn distortion(&self) -> [f64; 5] {
        self.lens.0
    }
    fn mechanical_errors(&self, index: usize) -> Option<MechanicalErrors> {
        self.axes.get(index).and_then(|a| a.mechanics())
    }
}
