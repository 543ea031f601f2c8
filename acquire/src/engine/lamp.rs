//! The lamp monitor: every measurement records the lamp's measured voltage and current
//! (lights whose supply measures, see `gonio_devices::Light::read_back`), compares them with
//! the run's reference reading, warns and counts when they drift beyond the rig file's
//! threshold, and gives the output correction when the rig file has a calibrated exponent
//! (see `gonio_devices::rig::LampMonitor` for the options and the formula).

use gonio_dataset::store::LampRecord;
use gonio_devices::rig::LampMonitor;
use gonio_devices::LampReading;

/// The monitor of one run.
#[derive(Clone, Debug)]
pub struct LampWatch {
    monitor: LampMonitor,
    reference: Option<LampReading>,
    warnings: usize,
}

impl LampWatch {
    pub fn new(monitor: LampMonitor) -> Self {
        LampWatch {
            monitor,
            reference: None,
            warnings: 0,
        }
    }

    /// Set the reference: the first reading of the run, once the lamp is on and settled.
    pub fn set_reference(&mut self, r: LampReading) {
        if r.current_a.is_nan() || r.current_a <= 0.0 {
            tracing::warn!(
                "lamp: the reference reading is {:.3} V, {:.4} A: no current flows; drift is measured from it all the same",
                r.voltage_v,
                r.current_a
            );
        }
        self.reference = Some(r);
    }

    pub fn reference(&self) -> Option<LampReading> {
        self.reference
    }

    /// Measurements whose drift exceeded the threshold so far.
    pub fn warnings(&self) -> usize {
        self.warnings
    }

    /// The record of measurement `index` with reading `r` (the first reading becomes the
    /// reference when none was set).
    pub fn observe(&mut self, index: usize, r: LampReading) -> LampRecord {
        let reference = *self.reference.get_or_insert(r);
        let rel = |x: f64, x0: f64| if x0 > 0.0 { x / x0 - 1.0 } else { 0.0 };
        let current_drift = rel(r.current_a, reference.current_a);
        let voltage_drift = rel(r.voltage_v, reference.voltage_v);
        let t = self.monitor.drift_threshold;
        let drift_warning = current_drift.abs() > t || voltage_drift.abs() > t;
        if drift_warning {
            self.warnings += 1;
            tracing::warn!(
                measurement = index,
                "lamp drift beyond {:.1} %: {:.3} V ({:+.2} %), {:.4} A ({:+.2} %) against {:.3} V, {:.4} A at the start",
                t * 100.0,
                r.voltage_v,
                voltage_drift * 100.0,
                r.current_a,
                current_drift * 100.0,
                reference.voltage_v,
                reference.current_a
            );
        }
        let output_correction = self
            .monitor
            .output_exponent
            .filter(|_| reference.current_a > 0.0 && r.current_a > 0.0)
            .map(|k| (r.current_a / reference.current_a).powf(k));
        LampRecord {
            voltage_v: r.voltage_v,
            current_a: r.current_a,
            current_drift,
            voltage_drift,
            drift_warning,
            output_correction,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn reading(v: f64, i: f64) -> LampReading {
        LampReading {
            voltage_v: v,
            current_a: i,
        }
    }

    #[test]
    fn drift_beyond_the_threshold_warns_and_counts() {
        let mut w = LampWatch::new(LampMonitor {
            drift_threshold: 0.02,
            output_exponent: None,
        });
        w.set_reference(reading(12.0, 8.0));
        let a = w.observe(0, reading(12.0, 7.9));
        assert!(!a.drift_warning && a.output_correction.is_none());
        assert!((a.current_drift + 0.0125).abs() < 1e-12);
        let b = w.observe(1, reading(12.0, 7.8));
        assert!(b.drift_warning, "{b:?}");
        let c = w.observe(2, reading(12.5, 8.0));
        assert!(c.drift_warning, "voltage drift counts too: {c:?}");
        assert_eq!(w.warnings(), 2);
    }

    #[test]
    fn correction_only_with_a_calibrated_exponent() {
        let mut w = LampWatch::new(LampMonitor {
            drift_threshold: 0.5,
            output_exponent: Some(3.0),
        });
        let first = w.observe(0, reading(12.0, 8.0));
        assert_eq!(first.output_correction, Some(1.0), "the first reading is the reference");
        let r = w.observe(1, reading(12.0, 7.2));
        assert!((r.output_correction.unwrap() - 0.9f64.powi(3)).abs() < 1e-12);
    }
}
