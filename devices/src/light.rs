//! The light trait: a lamp that can be switched and dimmed, and (where its supply can
//! measure) read back.

use crate::DeviceError;
use async_trait::async_trait;
use serde::{Deserialize, Serialize};

/// What the lamp's supply measures at its output: the electrical state of the lamp.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LampReading {
    /// Output voltage (V).
    pub voltage_v: f64,
    /// Output current (A).
    pub current_a: f64,
}

#[async_trait]
pub trait Light: Send + Sync {
    fn name(&self) -> &str;
    /// Switch on with a relative intensity in [0, 1] (0 switches off).
    async fn set(&self, on: bool, intensity: f64) -> Result<(), DeviceError>;
    /// Who the lamp's supply says it is (SCPI `*IDN?`: maker, model, serial, firmware);
    /// a light without one answers with its name.
    async fn identity(&self) -> Result<String, DeviceError> {
        Ok(self.name().to_string())
    }
    /// The measured voltage and current, or `None` for a light that measures nothing
    /// (then nothing is recorded).
    async fn read_back(&self) -> Result<Option<LampReading>, DeviceError> {
        Ok(None)
    }
}
