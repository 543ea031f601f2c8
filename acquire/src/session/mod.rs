//! The acquisition session: what `gonio acquire` does around the engine, as a library, so
//! the CLI, the tests, the web monitor and batch runners all acquire the same way.
//!
//! - [`Session::create`]: apply and validate the exposure bracketing asked for (`--hdr`,
//!   [`apply_hdr`]), load the calibration (a rig-geometry result corrects the rig's
//!   kinematics before anything is planned), plan, create the dataset (manifest header with
//!   the run settings, `plan.json`, copies of the applied calibration results);
//! - [`Session::resume`]: reopen an interrupted dataset with its own rig, sample, plan and
//!   calibration copies, and measure only what is missing;
//! - [`Session::run`]: record the skipped pairs once, build the rig and the
//!   [`Developer`](crate::develop::Developer), run the engine (optionally only `limit`
//!   measurements), and return the [`Summary`]; a complete run finishes the manifest.
//!
//! Progress goes to an [`Observer`] (the engine's events); nothing here prints.

mod summary;

pub mod preflight;
pub use preflight::Preflight;
pub use summary::{peak_rss_mib, AdaptiveSummary, ReferenceSummary, Summary};

use crate::calibrate::apply::{load_dir, load_files, AppliedCalibration, LoadError, LoadedResult};
use crate::develop::rectify::RectifyParams;
use crate::develop::Developer;
use crate::engine::{self, EngineError, Observer, RunOptions};
use crate::plan::adaptive::{
    analysis_row, analysis_texels, AdaptiveInfo, AdaptiveRequest, AdaptiveStop, AdaptiveTuning,
};
use crate::plan::sparse::{units_key, SparseDesign, SparseRequest, SparseTarget};
use crate::plan::{Plan, PlanError, PlanOptions, Step};
use crate::rig::{Rig, RigBuildError};
use gonio_dataset::shard::ShardInfo;
use gonio_dataset::store::{self, Dataset, ManifestHeader, StoreError};
use gonio_dataset::sweep::Sweep;
use gonio_devices::hdr::{HdrMode, HdrSpec};
use gonio_devices::rig::RigSpec;
use gonio_devices::Direction;
use gonio_simulator::{RenderQuality, SampleSpec, SimOptions};
use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use thiserror::Error;

/// Supersampling cap of the rectification filter in acquisitions.
pub const MAX_SUPERSAMPLE: usize = 8;

/// Why a session could not be created, resumed or run. Each names the dataset or input
/// and says how to go on.
#[derive(Debug, Error)]
pub enum SessionError {
    #[error("creating dataset {dir} (use --force to replace a dataset, --resume to continue one)")]
    Create { dir: String, source: Box<StoreError> },
    #[error("resuming dataset {dir}")]
    Resume { dir: String, source: Box<StoreError> },
    #[error("dataset {dir}: {what}")]
    Store {
        dir: String,
        what: String,
        source: Box<StoreError>,
    },
    #[error("planning the sweep")]
    Plan(#[source] PlanError),
    #[error("dataset {dir}: {message}")]
    Invalid { dir: String, message: String },
    #[error("dataset {dir}: {what}")]
    Json {
        dir: String,
        what: String,
        source: serde_json::Error,
    },
    #[error("loading the calibration of {dir}")]
    DatasetCalibration { dir: String, source: Box<LoadError> },
    #[error(transparent)]
    Calibration(Box<LoadError>),
    #[error("building the rig")]
    Rig(#[source] RigBuildError),
    /// The rig's `[hdr]` (after [`NewSession::hdr`]) has a bad value.
    #[error("rig `{rig}`: {key} = {value}: {message}")]
    Hdr {
        rig: String,
        key: String,
        value: String,
        message: String,
    },
    /// The engine stopped; the journal is consistent, so the dataset can be resumed.
    #[error("the journal is consistent; fix the cause and run `gonio acquire --resume {dir}`")]
    Engine { dir: String, source: Box<EngineError> },
}

impl From<LoadError> for SessionError {
    fn from(e: LoadError) -> Self {
        SessionError::Calibration(Box::new(e))
    }
}

/// Settings recorded in the manifest so `--resume` rebuilds the same rig.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunSettings {
    pub width: usize,
    pub height: usize,
    pub noise: bool,
    pub truth: bool,
    pub seed: Option<u64>,
    pub raw: bool,
    #[serde(default)]
    pub store_truth: bool,
    /// Drift references (`--reference-every`, `--reference-pair`); the manifest keeps
    /// them, so `--resume` continues the same schedule. Absent: none (and the manifest's
    /// bytes are those of a run without the feature).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reference: Option<ReferenceSettings>,
}

/// When and what the drift references measure (see `crate::engine::reference`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReferenceSettings {
    /// Minutes of rig time between references (`--reference-every`), finite and > 0.
    pub every_min: f64,
    /// The reference pair as [light index, view index] into the sweep
    /// (`--reference-pair`); `None` asks for the plan's first measured step, and the
    /// created dataset records which pair that was.
    #[serde(default)]
    pub pair: Option<[usize; 2]>,
}

impl ReferenceSettings {
    /// The reference pair's step of `plan`, checking the settings (the flag names are
    /// the CLI's: the settings come from there or from a manifest they wrote).
    pub fn resolve(&self, plan: &Plan) -> Result<(Step, [usize; 2]), String> {
        if !(self.every_min.is_finite() && self.every_min > 0.0) {
            return Err(format!(
                "--reference-every {}: must be a finite number of minutes > 0 (e.g. 30); \
                 leave the flag out to take no references",
                self.every_min
            ));
        }
        let step = match self.pair {
            None => plan.steps.first().ok_or_else(|| {
                "--reference-every: the plan measures no pair, so there is no reference pair".to_string()
            })?,
            Some([l, v]) => {
                if l >= plan.light_count || v * plan.light_count.max(1) >= plan.pairs.max(1) {
                    return Err(format!(
                        "--reference-pair {l},{v}: the sweep has light indices 0..{} and view indices 0..{}",
                        plan.light_count,
                        plan.pairs / plan.light_count.max(1)
                    ));
                }
                let index = v * plan.light_count + l;
                plan.steps.iter().find(|s| s.index == index).ok_or_else(|| {
                    format!(
                        "--reference-pair {l},{v}: pair {index} is not measured by this plan (skipped as \
                         infeasible, or left out by a sparse design); choose a measured pair, or leave the \
                         flag out for the plan's first"
                    )
                })?
            }
        };
        Ok((step.clone(), [step.light_index, step.view_index]))
    }
}

/// How to plan a new session.
#[derive(Clone, Debug)]
pub struct PlanRequest {
    pub options: PlanOptions,
    /// Plan one pair per isotropy class (also when the sample declares `isotropic = true`).
    pub isotropic: bool,
    /// A sparse acquisition: measure only the pairs a design in a prior chooses.
    pub sparse: Option<SparsePlan>,
    /// Fly-scan: expose while the lamp moves, within this blur bound ([`Plan::into_fly`]).
    pub fly: Option<crate::plan::fly::FlyOptions>,
}

/// A sparse acquisition's prior and how much to measure ([`Plan::build_sparse`]).
#[derive(Clone)]
pub struct SparsePlan {
    pub prior: std::sync::Arc<gonio_sparse::Prior>,
    /// How `plan.json` names the prior (its path).
    pub prior_name: String,
    pub target: SparseTarget,
    pub design: SparseDesign,
    /// `--adaptive`: measure in rounds until this stop ([`crate::plan::adaptive`]); the
    /// target and design above are then unused.
    pub adaptive: Option<AdaptiveStop>,
    /// The adaptive rounds' declared knobs (defaults unless `--residual-weight`/`--round-allowance`).
    pub adaptive_tuning: AdaptiveTuning,
}

impl std::fmt::Debug for SparsePlan {
    // The prior's basis is megabytes of numbers: name it instead.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SparsePlan")
            .field("prior", &self.prior_name)
            .field("target", &self.target)
            .field("design", &self.design)
            .field("adaptive", &self.adaptive)
            .finish()
    }
}

/// A new acquisition: where, with what, how.
#[derive(Clone, Debug)]
pub struct NewSession {
    pub out: PathBuf,
    /// Replace an existing gonio dataset at `out`.
    pub force: bool,
    /// The rig file as loaded (`hdr` sets its bracketing, a rig-geometry calibration in
    /// `calibration` corrects it).
    pub rig: RigSpec,
    /// Exposure bracketing per measurement (`--hdr off|auto|N`); `None`: the rig file's
    /// `[hdr] mode`, else off. Applied by [`apply_hdr`] and validated against the rig's
    /// base exposure by [`Session::create`].
    pub hdr: Option<HdrMode>,
    pub sample: SampleSpec,
    pub sweep: Sweep,
    pub plan: PlanRequest,
    pub settings: RunSettings,
    /// Directory of calibration results to apply.
    pub calibration: Option<PathBuf>,
    /// Measure only this shard's views (the whole sweep is planned; `gonio merge` joins
    /// the parts). Recorded as `extra.shard` in the manifest.
    pub shard: Option<gonio_dataset::shard::Shard>,
}

/// The rig with a bracketing mode applied: `None`, or `off` on a rig without `[hdr]`, leaves
/// it unchanged (so the manifest's rig snapshot is the rig file's); any other mode sets
/// `[hdr] mode`, keeping the rig file's limits or the defaults.
pub fn apply_hdr(rig: &mut RigSpec, mode: Option<HdrMode>) {
    match (mode, &mut rig.hdr) {
        (None, _) | (Some(HdrMode::Off), None) => {}
        (Some(m), Some(h)) => h.mode = m.word(),
        (Some(m), None) => {
            rig.hdr = Some(HdrSpec {
                mode: m.word(),
                ..HdrSpec::default()
            })
        }
    }
}

/// How one run of a session goes.
#[derive(Clone, Debug, Default)]
pub struct RunRequest {
    /// Pace the simulated rig in real time.
    pub realtime: bool,
    /// Stop after this many measurements (the dataset stays resumable).
    pub limit: Option<usize>,
}

/// An open acquisition: its dataset and everything needed to continue it.
pub struct Session {
    rig: RigSpec,
    sample: SampleSpec,
    plan: Plan,
    settings: RunSettings,
    dataset: Dataset,
    done: HashSet<usize>,
    /// The views this session measures (all without a shard).
    shard: Option<ShardInfo>,
    /// An adaptive acquisition's prior (its later rounds are chosen in it).
    prior: Option<Arc<gonio_sparse::Prior>>,
}

impl Session {
    /// Plan and create a new dataset (see the module docs).
    pub fn create(new: &NewSession) -> Result<Session, SessionError> {
        let mut rig = new.rig.clone();
        apply_hdr(&mut rig, new.hdr);
        if let Some(h) = &rig.hdr {
            h.validate(rig.camera.exposure_s)
                .map_err(|(key, value, message)| SessionError::Hdr {
                    rig: rig.name.clone(),
                    key,
                    value,
                    message,
                })?;
        }
        // A rig-geometry calibration corrects the kinematics before anything is planned.
        let calibration = match &new.calibration {
            Some(dir) => Some(load_dir(dir, &rig.name)?),
            None => None,
        };
        if let Some(results) = &calibration {
            let (applied, _) = AppliedCalibration::from_results(results)?;
            applied.correct_rig(&mut rig);
        }
        // A sample that declares `isotropic = true` gets the reduced plan; the plan
        // records it (and the time saved) like `--isotropic` does.
        let plan = if new.plan.isotropic || new.sample.isotropic {
            Plan::build_isotropic(&rig, &new.sweep, &new.plan.options)
        } else {
            Plan::build(&rig, &new.sweep, &new.plan.options)
        }
        .map_err(SessionError::Plan)?;
        let out = new.out.display().to_string();
        let shard = match new.shard {
            None => None,
            Some(s) => {
                let invalid = |message: String| SessionError::Invalid {
                    dir: out.clone(),
                    message,
                };
                if plan.isotropic.is_some() {
                    return Err(invalid(format!(
                        "--shard {s} with an isotropic plan: its measured pairs stand for pairs of other views, \
                         so views cannot be split; acquire it in one process"
                    )));
                }
                if !rig.is_simulated() {
                    return Err(invalid(format!(
                        "--shard {s} on rig `{}`, which drives real hardware: shards are for simulated rigs \
                         (one physical rig measures one process's plan)",
                        rig.name
                    )));
                }
                s.check_views(new.sweep.views.len()).map_err(invalid)?;
                Some(s.info(new.sweep.views.len()))
            }
        };
        let json = |what: &str, e: serde_json::Error| SessionError::Json {
            dir: out.clone(),
            what: what.into(),
            source: e,
        };
        let settings = new.settings.clone();
        let mut header = ManifestHeader::new(
            serde_json::to_value(&rig).map_err(|e| json("the rig snapshot", e))?,
            serde_json::to_value(&new.sample).map_err(|e| json("the sample snapshot", e))?,
            new.sweep.manifest_json(plan.policy),
            settings.width,
            settings.height,
            "linear normalised sensor signal (DN / max DN), radiometrically uncalibrated",
        );
        // The seed the sensor uses: `--seed`, else the rig file's `camera.options.seed`, else 1.
        header.seed = match settings.seed {
            Some(seed) => seed,
            None => rig
                .camera
                .noise_seed()
                .map_err(|e| SessionError::Invalid {
                    dir: out.clone(),
                    message: format!("rig `{}`: {e}", rig.name),
                })?
                .unwrap_or(1),
        };
        header.raw_frames = settings.raw;
        header.extra = serde_json::json!({ "run_settings": settings });
        if let Some(info) = shard {
            header.extra["shard"] = serde_json::json!(info);
        }
        if let Some(results) = &calibration {
            describe_calibration(results, &rig, &mut header)?;
        }
        // A sparse acquisition measures what the design in the prior chooses among the
        // feasible pairs; the prior must model this sweep and the values this run stores.
        let plan = match &new.plan.sparse {
            None => plan,
            Some(sp) => {
                sp.prior.check_units(&units_key(&header.values)).map_err(|e| {
                    SessionError::Plan(PlanError::Sparse {
                        message: format!("prior {}: {e}", sp.prior_name),
                    })
                })?;
                match sp.adaptive {
                    Some(stop) => {
                        let refuse = |what: &str| {
                            Err(SessionError::Invalid {
                                dir: out.clone(),
                                message: format!(
                                    "--adaptive with {what}: an adaptive run chooses each round from all the \
                                     values measured before it, in one process and in stop-and-go order"
                                ),
                            })
                        };
                        if new.shard.is_some() {
                            return refuse("--shard");
                        }
                        if new.plan.fly.is_some() {
                            return refuse("--fly");
                        }
                        let req = AdaptiveRequest {
                            prior: &sp.prior,
                            prior_name: &sp.prior_name,
                            stop,
                            noise_var: sp.prior.header.residual_var,
                            tuning: sp.adaptive_tuning,
                        };
                        Plan::build_adaptive(&rig, &new.sweep, &new.plan.options, &plan, req)
                            .map_err(SessionError::Plan)?
                    }
                    None => {
                        let req = SparseRequest {
                            prior: &sp.prior,
                            prior_name: &sp.prior_name,
                            target: sp.target,
                            noise_var: sp.prior.header.residual_var,
                            design: sp.design,
                        };
                        Plan::build_sparse(&rig, &new.sweep, &new.plan.options, &plan, req)
                            .map_err(SessionError::Plan)?
                    }
                }
            }
        };
        let plan = match new.plan.fly {
            None => plan,
            Some(fly) => plan
                .into_fly(&rig, &new.plan.options, fly)
                .map_err(SessionError::Plan)?,
        };
        // Drift references: the pair resolved in the final plan and recorded, so a resumed
        // run measures the same one.
        let mut settings = settings;
        if let Some(r) = settings.reference.as_mut() {
            let invalid = |message: String| SessionError::Invalid {
                dir: out.clone(),
                message,
            };
            if new.shard.is_some() {
                return Err(invalid(
                    "--reference-every with --shard: each shard would track its own drift and `gonio merge` \
                     does not join references; acquire with references in one process"
                        .into(),
                ));
            }
            let (_, pair) = r.resolve(&plan).map_err(invalid)?;
            rig.light_settle_s()
                .map_err(|e| invalid(format!("rig `{}`: {e}", rig.name)))?;
            r.pair = Some(pair);
            header.extra["run_settings"] = serde_json::json!(settings);
        }
        let dataset = Dataset::create(&new.out, &header, new.force).map_err(|source| SessionError::Create {
            dir: out.clone(),
            source: Box::new(source),
        })?;
        let store_err = |what: String, source| SessionError::Store {
            dir: out.clone(),
            what,
            source: Box::new(source),
        };
        for r in calibration.iter().flatten() {
            dataset
                .store_calibration_copy(&r.kind, &r.bytes)
                .map_err(|e| store_err(format!("writing {}", store::calibration_rel_path(&r.kind)), e))?;
        }
        let bytes = serde_json::to_vec(&plan).map_err(|e| json("the plan", e))?;
        dataset
            .write_plan(&bytes)
            .map_err(|e| store_err("writing plan.json".into(), e))?;
        Ok(Session {
            rig,
            sample: new.sample.clone(),
            plan,
            settings,
            dataset,
            done: HashSet::new(),
            shard,
            prior: new
                .plan
                .sparse
                .as_ref()
                .filter(|sp| sp.adaptive.is_some())
                .map(|sp| sp.prior.clone()),
        })
    }

    /// Reopen the interrupted acquisition in `dir` (rig, sample, sweep, plan and
    /// calibration come from it).
    pub fn resume(dir: &Path) -> Result<Session, SessionError> {
        let name = dir.display().to_string();
        let (dataset, header, records) = Dataset::resume(dir).map_err(|source| SessionError::Resume {
            dir: name.clone(),
            source: Box::new(source),
        })?;
        let json = |what: &str, e: serde_json::Error| SessionError::Json {
            dir: name.clone(),
            what: what.into(),
            source: e,
        };
        let rig: RigSpec = serde_json::from_value(header.rig.clone())
            .map_err(|e| json("reading the rig snapshot from the manifest", e))?;
        let sample: SampleSpec = serde_json::from_value(header.sample.clone())
            .map_err(|e| json("reading the sample snapshot from the manifest", e))?;
        let stored = dataset.read_plan().map_err(|source| SessionError::Store {
            dir: name.clone(),
            what: "reading plan.json".into(),
            source: Box::new(source),
        })?;
        let plan: Plan = match stored {
            None if records.is_empty() => {
                // Interrupted between creating the dataset and writing its plan: nothing
                // was measured yet, so plan again from the manifest's snapshots.
                tracing::warn!(dir = %dir.display(), "plan.json missing in an empty dataset: planning again");
                let sweep = sweep_from_header(&header.sweep).map_err(|e| json("reading the sweep snapshot", e))?;
                let policy = serde_json::from_value(header.sweep["policy"].clone()).unwrap_or_default();
                let plan = Plan::build(
                    &rig,
                    &sweep,
                    &PlanOptions {
                        policy,
                        kicks: 0,
                        time_cap: None,
                        seed: 1,
                    },
                )
                .map_err(SessionError::Plan)?;
                let bytes = serde_json::to_vec(&plan).map_err(|e| json("the plan", e))?;
                dataset.write_plan(&bytes).map_err(|source| SessionError::Store {
                    dir: name.clone(),
                    what: "writing plan.json".into(),
                    source: Box::new(source),
                })?;
                plan
            }
            None => {
                return Err(SessionError::Invalid {
                    dir: name,
                    message: format!(
                        "holds {} records but no {}: the plan it was measured with is lost, so it cannot be resumed",
                        records.len(),
                        store::PLAN_FILE
                    ),
                })
            }
            Some(bytes) => serde_json::from_slice(&bytes).map_err(|e| json("parsing plan.json", e))?,
        };
        let settings: RunSettings = serde_json::from_value(header.extra["run_settings"].clone())
            .map_err(|e| json("reading run settings from the manifest", e))?;
        let done: HashSet<usize> = records.iter().map(|r| r.index).collect();
        let shard: Option<ShardInfo> = match header.extra.get("shard") {
            None => None,
            Some(v) => Some(serde_json::from_value(v.clone()).map_err(|e| json("reading extra.shard", e))?),
        };
        let prior = match plan.sparse.as_ref().filter(|sp| sp.adaptive.is_some()) {
            None => None,
            Some(sp) => {
                let p = gonio_sparse::Prior::load(Path::new(&sp.prior)).map_err(|e| SessionError::Invalid {
                    dir: name.clone(),
                    message: format!(
                        "its adaptive plan chose its rounds in prior {}, which cannot be read ({e}); \
                         restore that file to resume",
                        sp.prior
                    ),
                })?;
                Some(Arc::new(p))
            }
        };
        if done.len() > plan.pairs {
            return Err(SessionError::Invalid {
                dir: name,
                message: format!("holds {} records but its plan has {} pairs", done.len(), plan.pairs),
            });
        }
        Ok(Session {
            rig,
            sample,
            plan,
            settings,
            dataset,
            done,
            shard,
            prior,
        })
    }

    /// The dataset directory.
    pub fn dir(&self) -> &Path {
        self.dataset.dir()
    }

    /// The plan this session executes.
    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// What the rest of the run will take (planned bytes against the free space of the
    /// dataset's disk, planned end): call it before [`Session::run`] and refuse a run that
    /// does not fit ([`Preflight::fits`]).
    pub fn preflight(&self) -> Preflight {
        let s = &self.settings;
        // An HDR bracket's raw frames are all stored.
        let exposures = match (self.rig.hdr_mode(), &self.rig.hdr) {
            (HdrMode::Fixed(n), _) => n as usize,
            (HdrMode::Auto, Some(h)) => 1 + h.planned_extra_exposures.ceil().max(0.0) as usize,
            _ => 1,
        };
        let raw = s
            .raw
            .then_some((self.rig.camera.width, self.rig.camera.height, exposures));
        let per = preflight::bytes_per_measurement(s.width, s.height, s.store_truth, raw);
        let done: HashSet<usize> = self
            .done
            .iter()
            .copied()
            .chain(self.dataset.records().iter().map(|r| r.index))
            .collect();
        preflight::preflight(&self.plan, &done, per, self.dataset.dir())
    }

    /// Measurements already stored when the session was opened.
    pub fn done(&self) -> &HashSet<usize> {
        &self.done
    }

    /// Run the session's remaining measurements (see the module docs). `pause`: set it to
    /// stop at the next measurement boundary (Ctrl-C). A complete run finishes the manifest.
    pub async fn run(
        self,
        req: &RunRequest,
        pause: Arc<AtomicBool>,
        observer: Observer,
    ) -> Result<Summary, SessionError> {
        let Session {
            rig: rig_spec,
            sample,
            mut plan,
            settings,
            dataset,
            done,
            shard,
            prior,
        } = self;
        let dir = dataset.dir().to_path_buf();
        let name = dir.display().to_string();
        let sim = SimOptions {
            realtime: req.realtime,
            noise: Some(settings.noise),
            seed: settings.seed,
            quality: RenderQuality::default(),
        };
        let rig = Arc::new(Rig::build(&rig_spec, &sample, &sim).map_err(SessionError::Rig)?);
        let calibration = dataset_calibration(dataset.header(), &dir, &rig_spec)?;
        let params = RectifyParams {
            width: settings.width,
            height: settings.height,
            sample_mm: rig.sample_mm,
            max_supersample: MAX_SUPERSAMPLE,
        };
        let corrections = calibration
            .as_ref()
            .map(|c| c.developer_corrections())
            .unwrap_or_default();
        let truth_k = rig.truth.as_ref().and_then(|t| t.sensor()).map(|s| s.k());
        let developer = Developer::new(
            params,
            rig_spec.camera.intrinsics(),
            rig.border.clone(),
            corrections,
            truth_k,
        );
        let references = match &settings.reference {
            None => None,
            Some(r) => {
                let invalid = |message: String| SessionError::Invalid {
                    dir: name.clone(),
                    message,
                };
                let (step, _) = r.resolve(&plan).map_err(invalid)?;
                Some(engine::reference::ReferencePlan {
                    every_s: r.every_min * 60.0,
                    step,
                    // One home for the setting, `light.options.settle_s`: a driver that
                    // switches a real lamp waits it itself (the HMP supply does); the
                    // simulated lamp does not, so the engine charges it to the rig clock.
                    settle_s: if rig_spec.light.backend == "sim" {
                        rig_spec
                            .light_settle_s()
                            .map_err(|e| invalid(format!("rig `{}`: {e}", rig_spec.name)))?
                    } else {
                        0.0
                    },
                    drift_threshold: rig.lamp_monitor.drift_threshold,
                })
            }
        };
        let mut opts = RunOptions {
            developer: Arc::new(developer),
            raw_frames: settings.raw,
            truth: settings.truth,
            store_truth: settings.store_truth,
            references,
            reference_schedule: Default::default(),
        };
        let store_err = |what: String, source: StoreError| SessionError::Store {
            dir: name.clone(),
            what,
            source: Box::new(source),
        };
        // One engine run per adaptive round (one run for any other plan): the rig stays
        // connected, and each round's record is in plan.json before its first move.
        let mut dataset = dataset;
        let mut total: Option<engine::RunReport> = None;
        let mut limit_left = req.limit;
        let mut analysis_wall_s = 0.0;
        // The analysis texels' values of every pair read so far: each round reads only the
        // images measured since the last one.
        let mut analysis_cache = AnalysisCache::default();
        // The adaptive analysis weighs each measured pair by its noise under this sensor
        // model, as `gonio complete` does.
        let sensor = rig_spec.sensor_noise();
        let plan_shard = loop {
            let done_now: HashSet<usize> = done
                .iter()
                .copied()
                .chain(dataset.records().iter().map(|r| r.index))
                .collect();
            // A shard runs the steps of its views only. The others count as done for the
            // engine, so every step keeps its position in the whole plan (`order`) and the
            // single-process journal order is what `gonio merge` restores.
            let in_shard = |index: usize| {
                shard.is_none_or(|sh| (sh.first_view..sh.end_view).contains(&(index / plan.light_count.max(1))))
            };
            let mut plan_shard = plan.clone();
            plan_shard.steps.retain(|s| in_shard(s.index));
            plan_shard.skipped.retain(|s| in_shard(s.index));
            let others: HashSet<usize> = plan.steps.iter().map(|s| s.index).filter(|&i| !in_shard(i)).collect();
            let done_run: HashSet<usize> = done_now.union(&others).copied().collect();
            // Skipped pairs are recorded once, so the dataset says what it did not measure and why.
            for s in &plan_shard.skipped {
                if !done_now.contains(&s.index) {
                    let rec = engine::skipped_record(s.index, s.light_deg, s.view_deg, s.reason.to_string());
                    dataset
                        .store(rec, None, None)
                        .map_err(|source| store_err(format!("recording skipped pair {}", s.index), source))?;
                }
            }
            let mut plan_run = plan.clone();
            if let Some(limit) = limit_left {
                let mut left = limit;
                plan_run.steps.retain(|s| {
                    if done_run.contains(&s.index) {
                        return true;
                    }
                    if left == 0 {
                        return false;
                    }
                    left -= 1;
                    true
                });
            }
            let result = engine::run(
                rig.clone(),
                Arc::new(plan_run),
                dataset,
                done_run,
                opts.clone(),
                pause.clone(),
                observer.clone(),
            )
            .await;
            let (ds, mut report) = result.map_err(|(_, source)| SessionError::Engine {
                dir: name.clone(),
                source: Box::new(source),
            })?;
            dataset = ds;
            opts.reference_schedule.last_at = report.references.last_at;
            report.already_done -= others.len().min(report.already_done);
            if let Some(l) = limit_left.as_mut() {
                *l = l.saturating_sub(report.stored_this_run);
            }
            let go_on = report.complete && !report.paused && limit_left != Some(0);
            total = Some(match total.take() {
                None => report,
                Some(t) => add_reports(t, report),
            });
            let open = plan.adaptive().is_some_and(|a| a.finished.is_none());
            if !(open && go_on) {
                break plan_shard;
            }
            // Between rounds: analyse what is measured, record the next round (or the
            // stop), and only then move.
            let prior = prior.as_ref().ok_or_else(|| SessionError::Invalid {
                dir: name.clone(),
                message: "an adaptive plan without its prior".into(),
            })?;
            let t = std::time::Instant::now();
            let (measured, values, noise) = adaptive_values(&dataset, &plan, prior, &sensor, &mut analysis_cache)
                .map_err(|e| SessionError::Invalid {
                    dir: name.clone(),
                    message: format!("reading the measured values for the next round: {e}"),
                })?;
            let sweep = sweep_from_header(&dataset.header().sweep)
                .map_err(|e| json_err(&name, "reading the sweep snapshot", e))?;
            let ad = plan.adaptive().expect("open adaptive plan");
            let popts = PlanOptions {
                policy: plan.policy,
                kicks: ad.plan_kicks,
                time_cap: None,
                seed: ad.plan_seed,
            };
            let added = plan
                .adaptive_next(&rig_spec, &sweep, &popts, prior, &measured, &values, &noise)
                .map_err(SessionError::Plan)?;
            analysis_wall_s += t.elapsed().as_secs_f64();
            tracing::info!(
                seconds = t.elapsed().as_secs_f64(),
                added,
                "adaptive analysis between rounds"
            );
            let bytes = serde_json::to_vec(&plan).map_err(|e| json_err(&name, "the plan", e))?;
            dataset
                .write_plan(&bytes)
                .map_err(|e| store_err("writing plan.json".into(), e))?;
        };
        let report = total.expect("the engine ran at least once");
        let mut summary = Summary::new(
            &name,
            &rig_spec,
            &sample,
            &plan_shard,
            &done,
            &report,
            calibration.as_deref(),
        );
        summary.fly = summary::FlySummary::from_records(dataset.records());
        if let Some(r) = &settings.reference {
            summary.references = Some(summary::ReferenceSummary::new(
                r,
                dataset.references(),
                &report.references,
            ));
        }
        if let Some(ad) = plan.adaptive() {
            summary.complete &= ad.finished.is_some();
            summary.adaptive = Some(summary::AdaptiveSummary::new(ad, analysis_wall_s));
        }
        if summary.complete {
            let mut value = serde_json::to_value(&summary).map_err(|e| json_err(&name, "the summary", e))?;
            // In the manifest the dataset names itself relative to its own directory (`.`),
            // not by the path the command was given: a dataset's bytes do not depend on
            // where it was written (`gonio_dataset::store::provenance`). --json keeps the path.
            value["dataset"] = serde_json::Value::String(".".into());
            dataset
                .finish(&value)
                .map_err(|source| store_err("writing the final manifest".into(), source))?;
        }
        Ok(summary)
    }
}

fn json_err(dir: &str, what: &str, source: serde_json::Error) -> SessionError {
    SessionError::Json {
        dir: dir.to_string(),
        what: what.into(),
        source,
    }
}

/// Two engine runs as one (adaptive rounds): counts and times add up, the last run says
/// whether it paused or completed.
fn add_reports(mut a: engine::RunReport, b: engine::RunReport) -> engine::RunReport {
    a.stored_this_run += b.stored_this_run;
    a.remaining = b.remaining;
    a.paused = b.paused;
    a.complete = b.complete;
    a.rig_time_s += b.rig_time_s;
    a.wall_time_s += b.wall_time_s;
    a.truth_error.merge(&b.truth_error);
    a.homography_from_markers += b.homography_from_markers;
    a.homography_from_pose += b.homography_from_pose;
    let (s, t) = (&mut a.stage_seconds, &b.stage_seconds);
    s.motion += t.motion;
    s.capture += t.capture;
    s.rectify += t.rectify;
    s.truth += t.truth;
    s.store += t.store;
    a.lamp_drift_warnings += b.lamp_drift_warnings;
    if b.lamp_identity.is_some() {
        a.lamp_identity = b.lamp_identity;
    }
    a.references.taken += b.references.taken;
    a.references.overhead_s += b.references.overhead_s;
    a.references.warnings += b.references.warnings;
    a.references.last_at = b.references.last_at.or(a.references.last_at);
    a
}

/// The analysis texels' values (prior's value space) of the pairs read so far, and the
/// image size they were read at.
#[derive(Default)]
struct AnalysisCache {
    texels: Option<usize>,
    /// Per pair: its values at the analysis texels and its measurement noise
    /// ([`crate::plan::adaptive::analysis_row`]).
    values: std::collections::HashMap<usize, (Vec<f64>, f64)>,
}

/// The measured pairs of an adaptive plan's rounds, their values at the analysis texels
/// (rows in the order of the returned pairs, columns texel-major then channel, in the
/// prior's value space) and each pair's measurement noise under `sensor`. Pairs without an
/// image (failed, skipped) are left out.
///
/// Reads only the images `cache` does not hold yet, and keeps only the analysis texels of
/// each (not the image): at 256² the analysis once read every measured image again each
/// round and held them all (0.8 GB at 927 images).
fn adaptive_values(
    dataset: &Dataset,
    plan: &Plan,
    prior: &gonio_sparse::Prior,
    sensor: &gonio_devices::hdr::SensorNoise,
    cache: &mut AnalysisCache,
) -> Result<AnalysisInput, String> {
    use rayon::prelude::*;
    let ad: &AdaptiveInfo = plan.adaptive().ok_or("not an adaptive plan")?;
    let mut image_of = std::collections::HashMap::new();
    for r in dataset.records() {
        if let Some(img) = &r.image {
            image_of.insert(r.index, img.clone());
        }
    }
    let mut measured: Vec<usize> = ad.chosen().into_iter().filter(|p| image_of.contains_key(p)).collect();
    measured.sort_unstable();
    let dir = dataset.dir();
    let space = prior.space();
    let n_texels = ad.analysis_texels;
    let new: Vec<usize> = measured
        .iter()
        .copied()
        .filter(|p| !cache.values.contains_key(p))
        .collect();
    let read: Vec<(usize, usize, (Vec<f64>, f64))> = new
        .par_iter()
        .map(|&p| {
            let path = dir.join(&image_of[&p]);
            let img = store::exr_io::read_exr(&path).map_err(|e| format!("{}: {e}", path.display()))?;
            let texels = img.data.len() / 3;
            let pick = analysis_texels(texels, n_texels);
            Ok((p, texels, analysis_row(&img.data, &pick, space, sensor)))
        })
        .collect::<Result<_, String>>()?;
    for (p, texels, v) in read {
        if *cache.texels.get_or_insert(texels) != texels {
            return Err(format!(
                "the measured images differ in size: pair {p} has {texels} texels, earlier ones {}",
                cache.texels.unwrap_or(0)
            ));
        }
        cache.values.insert(p, v);
    }
    let cols = measured.first().map_or(0, |p| cache.values[p].0.len());
    let values = nalgebra::DMatrix::<f64>::from_fn(measured.len(), cols, |i, j| cache.values[&measured[i]].0[j]);
    let noise = measured.iter().map(|p| cache.values[p].1).collect();
    Ok((measured, values, noise))
}

/// What [`adaptive_values`] returns: the measured pairs, their values at the analysis
/// texels and their measurement noise, in the same order.
type AnalysisInput = (Vec<usize>, nalgebra::DMatrix<f64>, Vec<f64>);

/// Load the results for rig `rig` and describe them in the header: `calibration` = the
/// applied ids (comma-separated), `values` and `extra.value_unit` = the unit of the stored
/// values, `extra.calibrations` = every result found (kind, id, source file, copy in the
/// dataset, applied or not).
fn describe_calibration(results: &[LoadedResult], rig: &RigSpec, header: &mut ManifestHeader) -> Result<(), LoadError> {
    let (applied, not_applied) = AppliedCalibration::from_results(results)?;
    check_raw_correction(&applied, rig)?;
    for kind in &not_applied {
        tracing::warn!(kind = %kind, "calibration kind is not applied by acquire yet: recorded as not applied");
    }
    if !applied.ids.is_empty() {
        header.calibration = Some(applied.ids.join(","));
    }
    if applied.radiometric.is_some() {
        header.values = "BRDF (1/sr) per texel, radiometrically calibrated with a white standard \
                         (value / (K · exposure · gain · E(x)), E from the lamp position per texel)"
            .into();
    }
    if let Some(raw) = &applied.raw {
        let kinds = raw.kinds().join(", ");
        header.values = if applied.radiometric.is_some() {
            format!("{} Raw frames corrected first: {kinds}.", header.values)
        } else {
            format!(
                "linear values (½ exp g of the response curve's scale), raw frames corrected: {kinds}; \
                 no white standard, so not BRDF"
            )
        };
        header.extra["corrections"] = serde_json::json!(raw.sources);
    }
    header.extra["value_unit"] = serde_json::json!(applied.value_unit());
    header.extra["calibrations"] = serde_json::Value::Array(
        results
            .iter()
            .map(|r| {
                serde_json::json!({
                    "kind": r.kind,
                    "id": r.id,
                    "source": r.file.display().to_string(),
                    "file": store::calibration_rel_path(&r.kind),
                    "applied": !not_applied.contains(&r.kind),
                })
            })
            .collect(),
    );
    Ok(())
}

/// Refuse raw-frame corrections made on another camera (size, bit depth) before anything is
/// created; warn when the dark frames were taken at another exposure (dark current scales
/// with it).
fn check_raw_correction(applied: &AppliedCalibration, rig: &RigSpec) -> Result<(), LoadError> {
    let Some(raw) = &applied.raw else { return Ok(()) };
    let c = &rig.camera;
    raw.check_camera(c.width, c.height, c.bit_depth)?;
    if let Some(t) = raw.dark_exposure_s {
        if (t - c.exposure_s).abs() > 1e-3 * c.exposure_s.abs().max(1e-9) {
            tracing::warn!(
                dark_exposure_s = t,
                exposure_s = c.exposure_s,
                "the dark frame was taken at another exposure than the camera's: its dark current differs"
            );
        }
    }
    Ok(())
}

/// The calibration a dataset applies, from its own copies (new run and resume alike);
/// `None` for an uncalibrated dataset.
fn dataset_calibration(
    header: &ManifestHeader,
    dir: &Path,
    rig: &RigSpec,
) -> Result<Option<Arc<AppliedCalibration>>, SessionError> {
    let Some(list) = header.extra.get("calibrations").and_then(|v| v.as_array()) else {
        return Ok(None);
    };
    let files: Vec<PathBuf> = list
        .iter()
        .filter_map(|e| e.get("file").and_then(|f| f.as_str()))
        .map(|f| dir.join(f))
        .collect();
    let results = load_files(&files, &rig.name).map_err(|source| SessionError::DatasetCalibration {
        dir: dir.display().to_string(),
        source: Box::new(source),
    })?;
    let (applied, _) = AppliedCalibration::from_results(&results)?;
    check_raw_correction(&applied, rig)?;
    let expected = header.calibration.clone().unwrap_or_default();
    if applied.ids.join(",") != expected {
        return Err(SessionError::Invalid {
            dir: dir.display().to_string(),
            message: format!(
                "its calibration copies have ids {:?}, the manifest says {:?}",
                applied.ids.join(","),
                expected
            ),
        });
    }
    Ok(Some(Arc::new(applied)))
}

/// The sweep recorded in a manifest header (`lights_deg`, `views_deg`, degrees).
fn sweep_from_header(v: &serde_json::Value) -> Result<Sweep, serde_json::Error> {
    let list = |key: &str| -> Result<Vec<Direction>, serde_json::Error> {
        let raw: Vec<[f64; 2]> = serde_json::from_value(v[key].clone())?;
        Ok(raw.iter().map(|[t, p]| Direction::from_degrees(*t, *p)).collect())
    };
    Ok(Sweep {
        name: v["name"].as_str().unwrap_or("sweep").to_string(),
        lights: list("lights_deg")?,
        views: list("views_deg")?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hdr_is_applied_and_validated_by_the_session() {
        // off on a rig without [hdr] leaves it as the rig file says; a mode sets [hdr].
        let mut rig = RigSpec::default_rig();
        rig.hdr = None;
        apply_hdr(&mut rig, Some(HdrMode::Off));
        assert!(rig.hdr.is_none());
        apply_hdr(&mut rig, None);
        assert!(rig.hdr.is_none());
        apply_hdr(&mut rig, Some(HdrMode::Auto));
        assert_eq!(rig.hdr.as_ref().map(|h| h.mode()), Some(HdrMode::Auto));
        // a bad limit of the rig file is refused before anything is planned or written
        rig.hdr.as_mut().unwrap().step = 1.0;
        let tmp = tempfile::tempdir().unwrap();
        let new = NewSession {
            out: tmp.path().join("ds"),
            force: false,
            rig,
            hdr: Some(HdrMode::Fixed(3)),
            sample: SampleSpec::resolve("wallpaper").unwrap(),
            sweep: Sweep::resolve("fibonacci:2").unwrap(),
            plan: PlanRequest {
                options: PlanOptions::default(),
                isotropic: false,
                sparse: None,
                fly: None,
            },
            settings: RunSettings {
                width: 16,
                height: 16,
                noise: false,
                truth: false,
                seed: None,
                raw: false,
                store_truth: false,
                reference: None,
            },
            calibration: None,
            shard: None,
        };
        let e = Session::create(&new).err().expect("a bad [hdr] is refused");
        assert!(
            matches!(e, SessionError::Hdr { ref key, .. } if key == "hdr.step"),
            "{e}"
        );
        assert!(e.to_string().starts_with("rig `"), "{e}");
        assert!(!tmp.path().join("ds").exists());
    }
}
