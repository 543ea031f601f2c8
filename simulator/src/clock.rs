//! The simulated rig's clock.
//!
//! Virtual by default: a move "takes" its planned time by advancing a counter, so a
//! ten-hour sweep runs as fast as the renderer allows. With `realtime` the same waits are
//! real sleeps, so the rig behaves like hardware in time too.

use std::sync::Mutex;
use std::time::Duration;

pub struct SimClock {
    now: Mutex<f64>,
    realtime: bool,
}

impl SimClock {
    pub fn new(realtime: bool) -> Self {
        SimClock {
            now: Mutex::new(0.0),
            realtime,
        }
    }

    /// Seconds since the rig started.
    pub fn now(&self) -> f64 {
        *self.now.lock().expect("clock poisoned")
    }

    pub fn is_realtime(&self) -> bool {
        self.realtime
    }

    /// Wait until time `t` (never goes backwards; concurrent waiters end at the latest).
    pub async fn wait_until(&self, t: f64) {
        if self.realtime {
            let dt = t - self.now();
            if dt > 0.0 {
                tokio::time::sleep(Duration::from_secs_f64(dt)).await;
            }
        }
        let mut now = self.now.lock().expect("clock poisoned");
        if t > *now {
            *now = t;
        }
    }

    /// Wait for a duration from now.
    pub async fn wait(&self, dt: f64) {
        let t = self.now() + dt.max(0.0);
        self.wait_until(t).await;
    }
}
