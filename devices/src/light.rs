//! The light trait: a lamp that can be switched and dimmed.

use crate::DeviceError;
use async_trait::async_trait;

#[async_trait]
pub trait Light: Send + Sync {
    fn name(&self) -> &str;
    /// Switch on with a relative intensity in [0, 1] (0 switches off).
    async fn set(&self, on: bool, intensity: f64) -> Result<(), DeviceError>;
}
