//! `gonio batch slurm`: write (and with `--submit` submit) a Slurm job array that runs a
//! sharded command, plus a merge job that depends on it (see `crate::slurm`).

use crate::slurm::{self, RetryMode, ShardedKind, SlurmJob};
use anyhow::{bail, Context, Result};
use serde::Serialize;
use std::path::PathBuf;
use std::process::{Command, ExitCode};

#[derive(clap::Subcommand, Debug)]
pub enum BatchCommand {
    /// A Slurm job array (one task per shard) and a dependent merge job.
    Slurm(SlurmArgs),
}

#[derive(clap::Args, Debug)]
#[command(trailing_var_arg = true)]
pub struct SlurmArgs {
    /// Number of shards (array tasks).
    #[arg(long)]
    pub shards: usize,
    /// Work directory (on a filesystem every node sees): scripts, `parts/`, `logs/`.
    #[arg(long)]
    pub work: PathBuf,
    /// The merged result (dataset directory or .gbtf file; for `dataset generate`, the family
    /// directory every shard writes into).
    #[arg(long)]
    pub out: PathBuf,
    /// Submit with sbatch (array first, then the merge job with --dependency=afterany).
    #[arg(long)]
    pub submit: bool,
    /// Retries of a failed shard.
    #[arg(long, default_value_t = 1)]
    pub retries: u32,
    /// How a failed shard is retried: again inside its allocation, or requeued by Slurm.
    #[arg(long, value_enum, default_value = "in-job")]
    pub retry_mode: RetryMode,
    /// CPUs per shard (also its RAYON_NUM_THREADS).
    #[arg(long, default_value_t = 1)]
    pub cpus_per_task: usize,
    /// Extra sbatch option for both jobs, e.g. `--sbatch-option=--time=1:00:00`; repeatable.
    #[arg(long = "sbatch-option")]
    pub sbatch_options: Vec<String>,
    /// The gonio executable the jobs run (default: this one).
    #[arg(long)]
    pub gonio: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
    /// The command to shard, after `--`: `sim btf …`, `compress DATASET --method pvmf …` or
    /// `dataset generate SPEC` (without --shard and --out).
    #[arg(required = true, allow_hyphen_values = true)]
    pub command: Vec<String>,
}

#[derive(Serialize)]
struct Report {
    shards: usize,
    array_script: PathBuf,
    merge_script: PathBuf,
    parts: Vec<PathBuf>,
    out: PathBuf,
    retries: u32,
    retry_mode: RetryMode,
    /// Slurm job ids (with --submit).
    array_job: Option<String>,
    merge_job: Option<String>,
}

pub fn run(c: BatchCommand) -> Result<ExitCode> {
    match c {
        BatchCommand::Slurm(a) => slurm_run(a),
    }
}

fn slurm_run(a: SlurmArgs) -> Result<ExitCode> {
    let mut command = a.command.clone();
    if command.first().map(String::as_str) == Some("--") {
        command.remove(0);
    }
    let kind = ShardedKind::of(&command).map_err(anyhow::Error::msg)?;
    if !(1..=crate::shard::MAX_SHARDS).contains(&a.shards) {
        bail!(
            "--shards {}: valid range is 1 ..= {}",
            a.shards,
            crate::shard::MAX_SHARDS
        );
    }
    if a.retries > 10 {
        bail!("--retries {}: at most 10", a.retries);
    }
    if !(1..=1024).contains(&a.cpus_per_task) {
        bail!("--cpus-per-task {}: valid range is 1 ..= 1024", a.cpus_per_task);
    }
    let abs = |p: &PathBuf, what: &str| -> Result<PathBuf> {
        let p = std::path::absolute(p).with_context(|| format!("{what} {}", p.display()))?;
        let s = p.display().to_string();
        if s.contains(['"', '$', '`', '\\', '\n']) {
            bail!("{what} {s}: choose a path without \" $ ` \\ or newlines (it goes into a job script)");
        }
        Ok(p)
    };
    let work = abs(&a.work, "--work")?;
    let out = abs(&a.out, "--out")?;
    let gonio = match &a.gonio {
        Some(g) => abs(g, "--gonio")?,
        None => std::env::current_exe().context("finding this gonio executable")?,
    };
    // The input argument (a dataset, a family spec) must be absolute too: the jobs may
    // start elsewhere.
    let input = match kind {
        ShardedKind::CompressPvmf => Some((1, "dataset")),
        ShardedKind::DatasetGenerate => Some((2, "family spec")),
        ShardedKind::SimBtf => None,
    };
    if let Some((at, what)) = input {
        if let Some(arg) = command.get(at).filter(|d| !d.starts_with('-')) {
            let p = abs(&PathBuf::from(arg), what)?;
            command[at] = p.display().to_string();
        }
    }
    let job = SlurmJob {
        kind,
        args: command,
        shards: a.shards,
        work: work.clone(),
        out,
        gonio,
        retries: a.retries,
        retry_mode: a.retry_mode,
        cpus_per_task: a.cpus_per_task,
        sbatch_options: a.sbatch_options.clone(),
    };
    for d in ["parts", "logs"] {
        let p = work.join(d);
        std::fs::create_dir_all(&p).with_context(|| format!("creating {}", p.display()))?;
    }
    for (path, text) in [
        (job.array_script_path(), job.array_script()),
        (job.merge_script_path(), job.merge_script()),
    ] {
        std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
    }
    let mut report = Report {
        shards: a.shards,
        array_script: job.array_script_path(),
        merge_script: job.merge_script_path(),
        parts: (1..=a.shards).map(|i| job.part(i)).collect(),
        out: job.out.clone(),
        retries: a.retries,
        retry_mode: a.retry_mode,
        array_job: None,
        merge_job: None,
    };
    if a.submit {
        let sbatch = slurm::which("sbatch").context(
            "sbatch is not installed (not found in PATH): install Slurm's client (Debian/Ubuntu: \
             `apt-get install slurm-client`; on a cluster, run this on a login node), or submit the \
             written scripts yourself",
        )?;
        let submit = |args: &[String]| -> Result<String> {
            let o = Command::new(&sbatch)
                .args(args)
                .output()
                .with_context(|| format!("running {}", sbatch.display()))?;
            if !o.status.success() {
                bail!(
                    "sbatch {} failed ({}): {}",
                    args.join(" "),
                    o.status,
                    String::from_utf8_lossy(&o.stderr).trim()
                );
            }
            // --parsable prints `jobid[;cluster]`.
            let id = String::from_utf8_lossy(&o.stdout)
                .trim()
                .split(';')
                .next()
                .unwrap_or("")
                .to_string();
            if id.is_empty() {
                bail!("sbatch {} printed no job id", args.join(" "));
            }
            Ok(id)
        };
        let array = submit(&["--parsable".into(), job.array_script_path().display().to_string()])?;
        let merge = submit(&[
            "--parsable".into(),
            format!("--dependency=afterany:{array}"),
            job.merge_script_path().display().to_string(),
        ])?;
        report.array_job = Some(array);
        report.merge_job = Some(merge);
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!("array script   {}", report.array_script.display());
        println!("merge script   {}", report.merge_script.display());
        println!(
            "parts          {}/part-1 … part-{}",
            work.join("parts").display(),
            a.shards
        );
        println!("merged result  {}", report.out.display());
        match (&report.array_job, &report.merge_job) {
            (Some(j), Some(m)) => println!("submitted      array job {j}, merge job {m} (afterany:{j})"),
            _ => println!(
                "submit with    J=$(sbatch --parsable {}) && sbatch --dependency=afterany:$J {}",
                report.array_script.display(),
                report.merge_script.display()
            ),
        }
    }
    Ok(ExitCode::SUCCESS)
}
