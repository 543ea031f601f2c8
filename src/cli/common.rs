//! Options shared by several subcommands: which rig, which sample, which sweep.

use anyhow::{Context, Result};
use gonio_acquire::plan::{Plan, PlanOptions, Policy};
use gonio_dataset::sweep::Sweep;
use gonio_devices::rig::RigSpec;
use gonio_simulator::SampleSpec;
use std::path::PathBuf;
use std::time::Duration;

/// Sides of an acquired or rendered image (`--size` of acquire and the benchmarks driving it).
pub const IMAGE_SIDES: std::ops::RangeInclusive<usize> = 8..=8192;

/// The one parser of `--size WxH` (`x` or `X`, e.g. `256x256`): whole numbers, each side in
/// `sides`. Errors name the value, for clap or for `--size` context.
pub fn parse_size(s: &str, sides: std::ops::RangeInclusive<usize>) -> std::result::Result<(usize, usize), String> {
    let (a, b) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("`{s}`: expected WxH, e.g. 256x256"))?;
    let w: usize = a.trim().parse().map_err(|_| format!("`{s}`: width is not a number"))?;
    let h: usize = b.trim().parse().map_err(|_| format!("`{s}`: height is not a number"))?;
    if !sides.contains(&w) || !sides.contains(&h) {
        return Err(match sides.end() {
            &usize::MAX => format!("`{s}`: each side must be at least {}", sides.start()),
            end => format!("`{s}`: each side must be {} ..= {end}", sides.start()),
        });
    }
    Ok((w, h))
}

#[derive(clap::Args, Debug, Clone)]
pub struct RigArgs {
    /// Rig file (TOML, see devices/rigs/); default: the embedded simulated two-arm rig.
    #[arg(long)]
    pub rig: Option<PathBuf>,
}

impl RigArgs {
    pub fn load(&self) -> Result<RigSpec> {
        match &self.rig {
            None => Ok(RigSpec::default_rig()),
            Some(p) => RigSpec::load(p).with_context(|| format!("loading rig {}", p.display())),
        }
    }
}

#[derive(clap::Args, Debug, Clone)]
pub struct SweepArgs {
    /// `bonn81` (default), `uniform15`, `bonn151` (Bonn's Dome), `fibonacci:N`, or a .toml/.csv direction list.
    #[arg(long, default_value = "bonn81")]
    pub sweep: String,
    /// What to do with pairs the rig cannot measure: `skip` or `substitute`.
    #[arg(long, default_value = "skip")]
    pub policy: Policy,
    /// Kicks (improvement steps) of the order optimizer: a work count, so the same inputs
    /// give the same plan on any machine and under any load.
    #[arg(long, default_value_t = gonio_acquire::plan::order::DEFAULT_KICKS)]
    pub plan_kicks: usize,
    /// Optional wall-clock cap (seconds) on the order optimizer. The plan then depends on
    /// the machine's speed and load; plan.json records the cap (`budget.time_cap_s`).
    #[arg(long)]
    pub plan_time: Option<f64>,
    #[arg(long, default_value_t = 1)]
    pub plan_seed: u64,
    /// The sample is isotropic: measure only pairs distinct in (θ_l, θ_v, |φ_l − φ_v|);
    /// export reconstructs the others (see `plan::isotropic`).
    #[arg(long)]
    pub isotropic: bool,
}

impl SweepArgs {
    pub fn load(&self) -> Result<Sweep> {
        Sweep::resolve(&self.sweep).with_context(|| format!("loading sweep `{}`", self.sweep))
    }
    /// The planner options these flags give (`--plan-time` and `--plan-kicks` checked).
    pub fn plan_options(&self) -> Result<PlanOptions> {
        if let Some(t) = self.plan_time {
            anyhow::ensure!(
                t.is_finite() && (0.0..=3600.0).contains(&t),
                "--plan-time {t}: must be between 0 and 3600 seconds (or leave it out: the \
                 default budget is --plan-kicks, which is reproducible)"
            );
        }
        anyhow::ensure!(
            self.plan_kicks <= 100_000_000,
            "--plan-kicks {}: at most 100000000",
            self.plan_kicks
        );
        Ok(PlanOptions {
            policy: self.policy,
            kicks: self.plan_kicks,
            time_cap: self.plan_time.map(Duration::from_secs_f64),
            seed: self.plan_seed,
        })
    }

    pub fn plan(&self, rig: &RigSpec, sweep: &Sweep) -> Result<Plan> {
        let opts = self.plan_options()?;
        if self.isotropic {
            return Ok(Plan::build_isotropic(rig, sweep, &opts)?);
        }
        Ok(Plan::build(rig, sweep, &opts)?)
    }
}

/// `--fly [--blur-deg B]`, shared by `gonio plan`, `gonio acquire` and the benches.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct FlyArgs {
    /// Fly-scan: expose while the lamp moves through each light ring (camera and sample
    /// stand still), instead of stopping at every pair; the lamp holds a constant velocity
    /// through each exposure and speeds up between distant poses (docs/results/rig-time.md).
    #[arg(long)]
    pub fly: bool,
    /// With --fly: the light direction one exposure may sweep, in degrees (0, 10]; it sets
    /// each ring's velocity. Default 0.5.
    #[arg(long, value_name = "DEG")]
    pub blur_deg: Option<f64>,
    /// With --fly: one constant velocity per flight (as serial stages fly) instead of a
    /// velocity profile per gap; for comparison.
    #[arg(long)]
    pub fly_constant_velocity: bool,
}

impl FlyArgs {
    /// The fly options these flags ask for (`None` without `--fly`).
    pub fn options(&self) -> Result<Option<gonio_acquire::plan::fly::FlyOptions>> {
        use gonio_acquire::plan::fly::{FlyOptions, DEFAULT_BLUR_DEG};
        match (self.fly, self.blur_deg) {
            (false, None) if !self.fly_constant_velocity => Ok(None),
            (false, Some(b)) => anyhow::bail!("--blur-deg {b} applies to fly-scan: add --fly"),
            (false, None) => {
                anyhow::bail!("--fly-constant-velocity applies to fly-scan: add --fly")
            }
            (true, b) => Ok(Some(
                FlyOptions::new(b.unwrap_or(DEFAULT_BLUR_DEG))?.with_constant_velocity(self.fly_constant_velocity),
            )),
        }
    }
}

pub fn load_sample(name: &str) -> Result<SampleSpec> {
    SampleSpec::resolve(name).with_context(|| format!("loading sample `{name}`"))
}

/// Parse `θ,φ` in degrees.
pub fn parse_angles(s: &str) -> std::result::Result<gonio_devices::Direction, String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let nums: Vec<f64> = parts.iter().filter_map(|p| p.parse().ok()).collect();
    if parts.len() != 2 || nums.len() != 2 {
        return Err(format!("`{s}`: expected `theta,phi` in degrees, e.g. `45,90`"));
    }
    if !(0.0..90.0).contains(&nums[0]) || !(0.0..360.0).contains(&nums[1]) {
        return Err(format!("`{s}`: θ must be in [0, 90) and φ in [0, 360) degrees"));
    }
    Ok(gonio_devices::Direction::from_degrees(nums[0], nums[1]))
}

/// Record `input` in an output's JSON object `obj` as `key` (its path relative to `out_dir`,
/// the output's directory) and `{key}_sha256` right after it (`gonio_dataset::store::provenance`:
/// same bytes wherever the files sit). Other keys keep their order. Its users (compress,
/// synthesize, complete, fit, the material exports) are all `btf` commands.
#[cfg(feature = "btf")]
pub fn record_input(
    obj: &mut serde_json::Value,
    key: &str,
    input: &std::path::Path,
    out_dir: &std::path::Path,
) -> Result<()> {
    let r = gonio_dataset::store::provenance::InputRef::new(input, out_dir)
        .with_context(|| format!("recording the input {} in the output", input.display()))?;
    gonio_dataset::store::provenance::record(obj, key, r.path, r.sha256);
    Ok(())
}
