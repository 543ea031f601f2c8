//! A family of synthetic datasets: one base sample, material parameters drawn from declared
//! ranges, one ground-truth BTF per member, and a table of labels (the true parameters)
//! next to the data: `gonio dataset generate SPEC.toml --out DIR`.
//!
//! Why: software that fits, compresses or classifies materials is tested on many samples
//! whose true parameters are known. A family is reproducible from its spec alone: member
//! `m`'s draws depend on (`seed`, `m`, the vary entry's position) only, never on which
//! process or shard renders it, so `--shard I/N` splits the members into disjoint
//! directories that together are byte for byte the single-process family.
//!
//! Layout of DIR:
//! - `family.toml`: the spec, verbatim (what the family is made from);
//! - `family.json`: format, spec, and per member its directory, sample name and labels;
//! - `labels.csv`: the same labels as a table (one row per member, vectors as `key[i]`);
//! - `members/NNNN/`: one gonio dataset per member (its manifest holds the member's whole
//!   sample spec and `extra.family` with its labels).
//!
//! Every process writes `family.toml`, `family.json` and `labels.csv` (identical bytes,
//! atomic renames), so shards need no lock. A member whose dataset is complete and made from
//! the same sample is kept, so a rerun resumes; a partial one is rendered again whole.

use super::dataset::{write_btf, BtfJob, BtfOutput, SynthError};
use gonio_dataset::shard::Shard;
use gonio_dataset::store::{self, StoreError};
use gonio_dataset::sweep::Sweep;
use gonio_devices::rig::RigSpec;
use gonio_simulator::SampleSpec;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Most members one family may have.
pub const MAX_MEMBERS: usize = 100_000;

/// The spec file (`SPEC.toml`).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FamilySpec {
    pub name: String,
    #[serde(default)]
    pub description: String,
    /// How many members (datasets).
    pub members: usize,
    /// Seed of every draw.
    #[serde(default)]
    pub seed: u64,
    /// The base sample: a built-in name or a sample TOML (relative to the spec file).
    pub sample: String,
    /// Rig file (relative to the spec file); default: the embedded simulated rig.
    #[serde(default)]
    pub rig: Option<PathBuf>,
    /// Sweep of every member (`bonn81`, `fibonacci:N`, …).
    #[serde(default = "default_sweep")]
    pub sweep: String,
    /// Texels per side.
    #[serde(default = "default_size")]
    pub size: usize,
    #[serde(default = "one")]
    pub supersample: usize,
    /// The parameters drawn per member.
    #[serde(default)]
    pub vary: Vec<Vary>,
}

fn default_sweep() -> String {
    "bonn81".into()
}
fn default_size() -> usize {
    64
}
fn one() -> usize {
    1
}

/// One drawn parameter: a dotted key into the sample's TOML (`material.0.alpha`,
/// `seed`, `height.amplitude_mm`) and exactly one distribution.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Vary {
    pub key: String,
    /// `[lo, hi]`: uniform; `lo` and `hi` may be vectors of equal length (per component).
    #[serde(default)]
    pub uniform: Option<[toml::Value; 2]>,
    /// `[lo, hi]`, both > 0: uniform in the logarithm (roughness, exponents).
    #[serde(default)]
    pub log_uniform: Option<[toml::Value; 2]>,
    /// `[lo, hi]`: a whole number, both ends included.
    #[serde(default)]
    pub integer: Option<[i64; 2]>,
    /// One of these values, each equally likely.
    #[serde(default)]
    pub choice: Option<Vec<toml::Value>>,
}

/// Why a family cannot be generated. Every variant names the spec, key or member.
#[derive(Debug, thiserror::Error)]
pub enum FamilyError {
    #[error("{file}: {message}")]
    Spec { file: String, message: String },
    #[error("{file}: vary key `{key}`: {message}")]
    Vary { file: String, key: String, message: String },
    #[error("member {member}: {message}")]
    Member { member: usize, message: String },
    #[error(
        "{dir}: member {member} is a complete dataset of another sample ({reason}); \
         the spec changed since it was generated: use another --out, or --force to replace it"
    )]
    Stale {
        dir: PathBuf,
        member: usize,
        reason: String,
    },
    #[error(
        "{dir} holds another family (its family.toml differs from {spec}); \
         use another --out, or --force to replace its members"
    )]
    OtherFamily { dir: PathBuf, spec: String },
    #[error("{0}")]
    Shard(String),
    #[error(transparent)]
    Synth(#[from] SynthError),
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// A spec read from its file, with what the members share resolved.
pub struct Family {
    pub spec: FamilySpec,
    /// The spec file's bytes (stored verbatim as `family.toml`).
    text: String,
    file: String,
    base: SampleSpec,
    rig: RigSpec,
    sweep: Sweep,
}

/// One member: its sample and its labels (key → the value the sample holds).
#[derive(Clone, Debug, Serialize)]
pub struct Member {
    pub member: usize,
    /// Directory relative to the family's.
    pub dir: String,
    pub sample: String,
    pub labels: serde_json::Map<String, serde_json::Value>,
    #[serde(skip)]
    pub spec: SampleSpec,
}

/// The state of a family directory ([`Family::check`]).
#[derive(Clone, Debug, Serialize)]
pub struct CheckReport {
    pub name: String,
    pub members: usize,
    pub complete: usize,
    /// Members with no complete dataset (never started, or interrupted).
    pub missing: Vec<usize>,
    /// Complete datasets of another sample: member and the first difference.
    pub stale: Vec<(usize, String)>,
}

impl CheckReport {
    pub fn is_complete(&self) -> bool {
        self.complete == self.members
    }
}

/// What a generation run did.
#[derive(Clone, Debug, Serialize)]
pub struct FamilyReport {
    pub name: String,
    pub members: usize,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shard: Option<String>,
    /// Members rendered by this run.
    pub rendered: Vec<usize>,
    /// Members already complete (kept).
    pub kept: Vec<usize>,
    pub images: usize,
    pub render_seconds: f64,
}

impl Family {
    /// Read and check a spec: every key must exist in the base sample and every member's
    /// sample must validate, so a bad spec fails before anything is rendered.
    pub fn load(path: &Path) -> Result<Family, FamilyError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| FamilyError::Spec {
            file: file.clone(),
            message: format!("cannot read it: {e}"),
        })?;
        Family::parse(&text, &file, path.parent().unwrap_or(Path::new(".")))
    }

    /// The same family with `members` members: the spec's top-level `members = N` line is
    /// rewritten, so the stored `family.toml` says what was generated. Member m's draws
    /// depend only on the seed and m, so the first members are unchanged.
    pub fn with_members(mut self, members: usize) -> Result<Family, FamilyError> {
        let bad = |message: String| FamilyError::Spec {
            file: self.file.clone(),
            message,
        };
        if members == 0 || members > MAX_MEMBERS {
            return Err(bad(format!("--members {members}: give 1 to {MAX_MEMBERS}")));
        }
        let mut found = false;
        let text: Vec<String> = self
            .text
            .lines()
            .map(|l| {
                let key = l.split('=').next().unwrap_or("").trim();
                if !found && key == "members" && !l.starts_with(char::is_whitespace) {
                    found = true;
                    format!("members = {members}")
                } else {
                    l.to_string()
                }
            })
            .collect();
        if !found {
            return Err(bad(
                "--members needs a top-level `members = N` line in the spec to rewrite".into(),
            ));
        }
        let mut text = text.join("\n");
        if self.text.ends_with('\n') {
            text.push('\n');
        }
        self.text = text;
        self.spec.members = members;
        Ok(self)
    }

    /// [`Family::load`] from text; relative paths resolve against `base_dir`.
    pub fn parse(text: &str, file: &str, base_dir: &Path) -> Result<Family, FamilyError> {
        let bad = |message: String| FamilyError::Spec {
            file: file.into(),
            message,
        };
        let spec: FamilySpec = toml::from_str(text).map_err(|e| bad(e.to_string()))?;
        if spec.members == 0 || spec.members > MAX_MEMBERS {
            return Err(bad(format!(
                "members = {}: valid range is 1 ..= {MAX_MEMBERS}",
                spec.members
            )));
        }
        if spec.name.is_empty()
            || !spec
                .name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
        {
            return Err(bad(format!(
                "name = {:?}: use letters, digits, '-', '_' and '.' (it names every member's sample)",
                spec.name
            )));
        }
        let resolve = |p: &str| {
            let q = Path::new(p);
            if q.is_relative() && q.extension().is_some() {
                base_dir.join(q).display().to_string()
            } else {
                p.to_string()
            }
        };
        let base = SampleSpec::resolve(&resolve(&spec.sample)).map_err(|e| bad(format!("sample: {e}")))?;
        let rig = match &spec.rig {
            None => RigSpec::default_rig(),
            Some(p) => {
                let p = if p.is_relative() { base_dir.join(p) } else { p.clone() };
                RigSpec::load(&p).map_err(|e| bad(format!("rig {}: {e}", p.display())))?
            }
        };
        let sweep = Sweep::resolve(&spec.sweep).map_err(|e| bad(format!("sweep `{}`: {e}", spec.sweep)))?;
        if !(8..=4096).contains(&spec.size) {
            return Err(bad(format!("size = {}: valid range is 8 ..= 4096", spec.size)));
        }
        if !(1..=16).contains(&spec.supersample) {
            return Err(bad(format!(
                "supersample = {}: valid range is 1 ..= 16",
                spec.supersample
            )));
        }
        for v in &spec.vary {
            v.check().map_err(|message| FamilyError::Vary {
                file: file.into(),
                key: v.key.clone(),
                message,
            })?;
        }
        let family = Family {
            spec,
            text: text.to_string(),
            file: file.to_string(),
            base,
            rig,
            sweep,
        };
        // Draw member 0 now: a key that does not exist, a type that does not fit or a value
        // the sample refuses is reported before any rendering.
        family.member(0)?;
        Ok(family)
    }

    /// Member `m`'s sample and labels.
    pub fn member(&self, m: usize) -> Result<Member, FamilyError> {
        let mut value = toml::Value::try_from(&self.base).map_err(|e| FamilyError::Member {
            member: m,
            message: format!("the base sample does not convert to TOML: {e}"),
        })?;
        // The family's seed is part of the name: a fresh draw of the same family with another
        // seed is another sample (a prior that saw `plastics-s7-0003` has not seen
        // `plastics-s8-0003`), while the directory stays `members/NNNN`.
        let name = format!(
            "{}-s{}-{}",
            self.spec.name,
            self.spec.seed,
            member_dir_name(m, self.spec.members)
        );
        set(&mut value, "name", toml::Value::String(name.clone())).expect("samples have a name");
        for (k, v) in self.spec.vary.iter().enumerate() {
            let drawn = v.draw(draw_seed(self.spec.seed, m, k));
            set(&mut value, &v.key, drawn).map_err(|message| FamilyError::Vary {
                file: self.file.clone(),
                key: v.key.clone(),
                message,
            })?;
        }
        let text = toml::to_string(&value).map_err(|e| FamilyError::Member {
            member: m,
            message: format!("cannot write its sample as TOML: {e}"),
        })?;
        let spec =
            SampleSpec::parse(&text, &format!("{} member {m}", self.file), None).map_err(|e| FamilyError::Member {
                member: m,
                message: format!("the drawn sample is invalid: {e} (narrow the ranges in [[vary]])"),
            })?;
        // The labels are what the sample holds after parsing (the truth the render used).
        let back = toml::Value::try_from(&spec).map_err(|e| FamilyError::Member {
            member: m,
            message: e.to_string(),
        })?;
        let mut labels = serde_json::Map::new();
        for v in &self.spec.vary {
            let got = get(&back, &v.key)
                .cloned()
                .unwrap_or(toml::Value::String(String::new()));
            labels.insert(v.key.clone(), toml_to_json(&got));
        }
        Ok(Member {
            member: m,
            dir: format!("members/{}", member_dir_name(m, self.spec.members)),
            sample: name,
            labels,
            spec,
        })
    }

    /// Generate the members of `shard` (all without one) into `out`.
    pub fn generate(
        &self,
        out: &Path,
        shard: Option<Shard>,
        force: bool,
        progress: &dyn Fn(usize),
    ) -> Result<FamilyReport, FamilyError> {
        let n = self.spec.members;
        let range = match shard {
            Some(s) => {
                if s.count > n {
                    return Err(FamilyError::Shard(format!(
                        "--shard {s}: {n} members cannot be split into {} shards (at most {n})",
                        s.count
                    )));
                }
                s.views(n)
            }
            None => 0..n,
        };
        std::fs::create_dir_all(out.join("members")).map_err(|e| StoreError::io("creating", out, None, e))?;
        let spec_path = out.join("family.toml");
        if let Ok(existing) = std::fs::read_to_string(&spec_path) {
            if existing != self.text && !force {
                return Err(FamilyError::OtherFamily {
                    dir: out.to_path_buf(),
                    spec: self.file.clone(),
                });
            }
        }
        let members = (0..n).map(|m| self.member(m)).collect::<Result<Vec<_>, _>>()?;
        store::atomic::write_atomic(&spec_path, self.text.as_bytes(), None)?;
        let index = serde_json::json!({
            "format": "gonio-family",
            "version": 1,
            "spec": self.spec,
            "members": members,
        });
        let json = serde_json::to_vec_pretty(&index).expect("family index serialises");
        store::atomic::write_atomic(&out.join("family.json"), &json, None)?;
        store::atomic::write_atomic(
            &out.join("labels.csv"),
            labels_csv(&self.spec, &members).as_bytes(),
            None,
        )?;

        let mut report = FamilyReport {
            name: self.spec.name.clone(),
            members: n,
            shard: shard.map(|s| s.to_string()),
            rendered: vec![],
            kept: vec![],
            images: 0,
            render_seconds: 0.0,
        };
        for member in &members[range] {
            let dir = out.join(&member.dir);
            if self.is_done(&dir, member, force)? {
                report.kept.push(member.member);
                continue;
            }
            if dir.exists() && !dir.join("manifest.json").exists() {
                // Only a crash inside `Dataset::create` leaves a member directory without
                // its manifest: nothing in it is complete, and the member is redone whole.
                tracing::warn!(dir = %dir.display(), "removing a partial member directory (no manifest.json)");
                std::fs::remove_dir_all(&dir).map_err(|e| StoreError::io("removing", &dir, None, e))?;
            }
            let job = BtfJob {
                rig: &self.rig,
                sample: &member.spec,
                sweep: &self.sweep,
                size: self.spec.size,
                supersample: self.spec.supersample,
                shard: None,
                per_pair: false,
            };
            let extra = serde_json::json!({ "family": {
                "name": self.spec.name, "member": member.member, "labels": member.labels,
            }});
            let stats = write_btf(
                &job,
                Some(BtfOutput {
                    dir: &dir,
                    force: true,
                    extra,
                }),
                &|| {},
            )?;
            report.images += stats.images;
            report.render_seconds += stats.render_seconds;
            report.rendered.push(member.member);
            progress(member.member);
        }
        Ok(report)
    }

    /// Which members of the family at `out` are complete, and which are missing, partial or
    /// of another sample (what a merge step of a sharded run reports by name).
    pub fn check(&self, out: &Path) -> Result<CheckReport, FamilyError> {
        let mut r = CheckReport {
            name: self.spec.name.clone(),
            members: self.spec.members,
            complete: 0,
            missing: vec![],
            stale: vec![],
        };
        for m in 0..self.spec.members {
            let member = self.member(m)?;
            match self.is_done(&out.join(&member.dir), &member, false) {
                Ok(true) => r.complete += 1,
                Ok(false) => r.missing.push(m),
                Err(FamilyError::Stale { reason, .. }) => r.stale.push((m, reason)),
                Err(e) => return Err(e),
            }
        }
        Ok(r)
    }

    /// A member already generated from the same sample: keep it. A partial one is redone;
    /// a complete one of another sample is refused unless `force`.
    fn is_done(&self, dir: &Path, member: &Member, force: bool) -> Result<bool, FamilyError> {
        if !dir.join("manifest.json").exists() {
            return Ok(false);
        }
        let (header, complete) = match store::read_header(dir) {
            Ok(h) => h,
            Err(_) => return Ok(false),
        };
        if !complete {
            return Ok(false);
        }
        let want = serde_json::to_value(&member.spec).expect("sample serialises");
        if header.sample == want && header.image_width == self.spec.size {
            return Ok(true);
        }
        if force {
            return Ok(false);
        }
        let reason = match gonio_dataset::shard::first_difference(&header.sample, &want) {
            Some((path, what)) => format!("sample differs at {path}: {what}"),
            None => format!("size {} instead of {}", header.image_width, self.spec.size),
        };
        Err(FamilyError::Stale {
            dir: dir.to_path_buf(),
            member: member.member,
            reason,
        })
    }
}

/// `0000`, `0001`, …: at least four digits, more when the family is larger.
fn member_dir_name(m: usize, members: usize) -> String {
    let width = (members.saturating_sub(1)).to_string().len().max(4);
    format!("{m:0width$}")
}

/// The seed of member `m`'s `k`-th draw: independent of how members are split between
/// processes.
fn draw_seed(seed: u64, m: usize, k: usize) -> u64 {
    let mut s = SplitMix(seed);
    let a = s.next() ^ (m as u64);
    let mut s = SplitMix(a);
    SplitMix(s.next() ^ (k as u64)).next()
}

/// SplitMix64 (Steele, Lea and Flood 2014): a tiny, well-mixed stream, enough for drawing a
/// handful of parameters, and the same on every platform.
struct SplitMix(u64);

impl SplitMix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1) with 53 random bits.
    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in `0..n` (`n` ≥ 1; multiply-shift, bias below n / 2⁶⁴).
    fn below(&mut self, n: u64) -> u64 {
        ((u128::from(self.next()) * u128::from(n)) >> 64) as u64
    }
}

fn as_f64(v: &toml::Value) -> Option<f64> {
    match v {
        toml::Value::Float(f) => Some(*f),
        toml::Value::Integer(i) => Some(*i as f64),
        _ => None,
    }
}

/// A range end as numbers: a scalar is one number, an array its elements.
fn numbers(v: &toml::Value) -> Option<Vec<f64>> {
    match v {
        toml::Value::Array(a) => a.iter().map(as_f64).collect(),
        x => as_f64(x).map(|f| vec![f]),
    }
}

impl Vary {
    fn check(&self) -> Result<(), String> {
        let given = [
            self.uniform.is_some(),
            self.log_uniform.is_some(),
            self.integer.is_some(),
            self.choice.is_some(),
        ];
        if given.iter().filter(|&&g| g).count() != 1 {
            return Err("give exactly one of uniform, log_uniform, integer, choice".into());
        }
        if self.key.is_empty() || self.key == "name" {
            return Err("the key must name a sample parameter (not `name`)".into());
        }
        let ranges = [(&self.uniform, false), (&self.log_uniform, true)];
        for (r, log) in ranges {
            let Some([lo, hi]) = r else { continue };
            let (Some(lo), Some(hi)) = (numbers(lo), numbers(hi)) else {
                return Err("range ends must be numbers, or arrays of numbers".into());
            };
            if lo.len() != hi.len() || lo.is_empty() {
                return Err(format!(
                    "range ends have {} and {} components; give equal lengths",
                    lo.len(),
                    hi.len()
                ));
            }
            for (a, b) in lo.iter().zip(&hi) {
                if !(a.is_finite() && b.is_finite() && a <= b) {
                    return Err(format!("range [{a}, {b}]: need finite lo ≤ hi"));
                }
                if log && *a <= 0.0 {
                    return Err(format!("log_uniform [{a}, {b}]: both ends must be > 0"));
                }
            }
        }
        if let Some([a, b]) = self.integer {
            if a > b {
                return Err(format!("integer [{a}, {b}]: need lo ≤ hi"));
            }
        }
        if let Some(c) = &self.choice {
            if c.is_empty() {
                return Err("choice is empty".into());
            }
        }
        Ok(())
    }

    /// The drawn value (checked by [`Vary::check`]).
    fn draw(&self, seed: u64) -> toml::Value {
        let mut rng = SplitMix(seed);
        let scalar_or_vec = |lo: &toml::Value, xs: Vec<f64>| {
            if matches!(lo, toml::Value::Array(_)) {
                toml::Value::Array(xs.into_iter().map(toml::Value::Float).collect())
            } else {
                toml::Value::Float(xs[0])
            }
        };
        if let Some([lo, hi]) = &self.uniform {
            let (a, b) = (numbers(lo).unwrap_or_default(), numbers(hi).unwrap_or_default());
            let xs = a.iter().zip(&b).map(|(a, b)| a + (b - a) * rng.unit()).collect();
            return scalar_or_vec(lo, xs);
        }
        if let Some([lo, hi]) = &self.log_uniform {
            let (a, b) = (numbers(lo).unwrap_or_default(), numbers(hi).unwrap_or_default());
            let xs = a
                .iter()
                .zip(&b)
                .map(|(a, b)| (a.ln() + (b.ln() - a.ln()) * rng.unit()).exp().clamp(*a, *b))
                .collect();
            return scalar_or_vec(lo, xs);
        }
        if let Some([a, b]) = self.integer {
            let span = (b as i128 - a as i128 + 1).min(u64::MAX as i128) as u64;
            return toml::Value::Integer((a as i128 + rng.below(span) as i128) as i64);
        }
        let c = self.choice.as_deref().unwrap_or_default();
        c[rng.below(c.len() as u64) as usize].clone()
    }
}

/// Set `key` (dotted; numeric parts index arrays) in `root`. The parent must exist; the
/// last part may be new in a table (an optional parameter).
fn set(root: &mut toml::Value, key: &str, value: toml::Value) -> Result<(), String> {
    let parts: Vec<&str> = key.split('.').collect();
    let (last, path) = parts.split_last().ok_or("empty key")?;
    let mut at = root;
    let mut walked = String::new();
    for p in path {
        at = step(at, p, &walked)?;
        walked = if walked.is_empty() {
            p.to_string()
        } else {
            format!("{walked}.{p}")
        };
    }
    let here = if walked.is_empty() {
        "the sample".to_string()
    } else {
        format!("`{walked}`")
    };
    match at {
        toml::Value::Table(t) => {
            if let Some(old) = t.get(*last) {
                check_type(old, &value)?;
            }
            t.insert(last.to_string(), value);
            Ok(())
        }
        toml::Value::Array(a) => {
            let i: usize = last
                .parse()
                .map_err(|_| format!("{here} is a list: index it with a number"))?;
            let n = a.len();
            let slot = a
                .get_mut(i)
                .ok_or_else(|| format!("{here} has {n} entries (0 ..= {})", n.saturating_sub(1)))?;
            check_type(slot, &value)?;
            *slot = value;
            Ok(())
        }
        _ => Err(format!("{here} is a single value, not a table")),
    }
}

fn step<'a>(at: &'a mut toml::Value, p: &str, walked: &str) -> Result<&'a mut toml::Value, String> {
    let here = if walked.is_empty() {
        "the sample".to_string()
    } else {
        format!("`{walked}`")
    };
    match at {
        toml::Value::Table(t) => {
            let keys = t.keys().cloned().collect::<Vec<_>>().join(", ");
            t.get_mut(p)
                .ok_or_else(|| format!("{here} has no `{p}` (it has: {keys})"))
        }
        toml::Value::Array(a) => {
            let n = a.len();
            let i: usize = p
                .parse()
                .map_err(|_| format!("{here} is a list: index it with a number"))?;
            a.get_mut(i)
                .ok_or_else(|| format!("{here} has {n} entries (0 ..= {})", n.saturating_sub(1)))
        }
        _ => Err(format!("{here} is a single value; `{p}` cannot be inside it")),
    }
}

/// A drawn number must replace a number of the same shape (a float may replace an
/// integer-valued float, never a string or a table).
fn check_type(old: &toml::Value, new: &toml::Value) -> Result<(), String> {
    use toml::Value::*;
    let ok = match (old, new) {
        (Float(_) | Integer(_), Float(_)) => true,
        (Integer(_), Integer(_)) | (Float(_), Integer(_)) => true,
        (String(_), String(_)) | (Boolean(_), Boolean(_)) => true,
        (Array(a), Array(b)) => a.len() == b.len(),
        // A whole table (e.g. `choice` of reliefs); the simulator checks its fields.
        (Table(_), Table(_)) => true,
        _ => false,
    };
    if ok {
        Ok(())
    } else {
        Err(format!(
            "the sample holds {} there, the draw gives {} (change the distribution)",
            describe(old),
            describe(new)
        ))
    }
}

fn describe(v: &toml::Value) -> String {
    match v {
        toml::Value::Array(a) => format!("a list of {}", a.len()),
        other => format!("a {}", other.type_str()),
    }
}

fn get<'a>(root: &'a toml::Value, key: &str) -> Option<&'a toml::Value> {
    key.split('.').try_fold(root, |at, p| match at {
        toml::Value::Table(t) => t.get(p),
        toml::Value::Array(a) => p.parse::<usize>().ok().and_then(|i| a.get(i)),
        _ => None,
    })
}

fn toml_to_json(v: &toml::Value) -> serde_json::Value {
    serde_json::to_value(v).unwrap_or(serde_json::Value::Null)
}

/// `labels.csv`: `member,dir,sample,<key>…` with vectors as `<key>[i]` columns.
fn labels_csv(spec: &FamilySpec, members: &[Member]) -> String {
    let width = |key: &str| {
        members
            .iter()
            .map(|m| m.labels.get(key).and_then(|v| v.as_array()).map_or(0, |a| a.len()))
            .max()
            .unwrap_or(0)
    };
    let mut header = vec!["member".to_string(), "dir".into(), "sample".into()];
    let mut cols: Vec<(String, Option<usize>)> = vec![];
    for v in &spec.vary {
        match width(&v.key) {
            0 => {
                header.push(v.key.clone());
                cols.push((v.key.clone(), None));
            }
            n => {
                for i in 0..n {
                    header.push(format!("{}[{i}]", v.key));
                    cols.push((v.key.clone(), Some(i)));
                }
            }
        }
    }
    let cell = |v: Option<&serde_json::Value>| match v {
        Some(serde_json::Value::String(s)) => csv_quote(s),
        Some(x) => x.to_string(),
        None => String::new(),
    };
    let mut s = header.iter().map(|h| csv_quote(h)).collect::<Vec<_>>().join(",") + "\n";
    for m in members {
        let mut row = vec![m.member.to_string(), csv_quote(&m.dir), csv_quote(&m.sample)];
        for (key, i) in &cols {
            let v = m.labels.get(key);
            row.push(match i {
                None => cell(v),
                Some(i) => cell(v.and_then(|v| v.get(*i))),
            });
        }
        s += &row.join(",");
        s.push('\n');
    }
    s
}

fn csv_quote(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

#[cfg(test)]
mod tests;
