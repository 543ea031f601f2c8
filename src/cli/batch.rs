//! `gonio batch slurm`: write (and with `--submit` submit) a Slurm job array that runs a
//! sharded command, plus a merge job that depends on it (see `crate::slurm`).

use super::compress::shard_kind;
use super::dataset::DatasetCommand;
use super::sim::SimCommand;
use super::{Cli, Command as Gonio};
use crate::slurm::{self, RetryMode, ShardedKind, SlurmJob};
use anyhow::{bail, Context, Result};
use clap::Parser;
use gonio_btf::compress::Shard;
use serde::Serialize;
use std::path::{Path, PathBuf};
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
    /// PCA, DFMF, local PCA: merge every round as a two-level tree, groups of F shards
    /// first (an array of `gonio merge --partial` jobs, in parallel), then the N/F group
    /// parts; F must divide --shards. Every merge then reads F or N/F parts instead of N
    /// (docs/guide/scale.md).
    #[arg(long, value_name = "F")]
    pub merge_fanout: Option<usize>,
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
    /// The last round's scripts (the only round, except for pca/dfmf/local-pca).
    array_script: PathBuf,
    merge_script: PathBuf,
    /// The last round's parts.
    parts: Vec<PathBuf>,
    out: PathBuf,
    retries: u32,
    retry_mode: RetryMode,
    /// Slurm job ids (with --submit) of the last round: its merge writes `out`.
    array_job: Option<String>,
    merge_job: Option<String>,
    /// Every round (pca/dfmf/local-pca: one per pass over the views, each array depending on
    /// the previous merge with afterok).
    rounds: Vec<Round>,
}

#[derive(Serialize)]
struct Round {
    array_script: PathBuf,
    /// The group merges of a tree merge (`--merge-fanout`).
    #[serde(skip_serializing_if = "Option::is_none")]
    group_script: Option<PathBuf>,
    merge_script: PathBuf,
    merged: PathBuf,
    array_job: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    group_job: Option<String>,
    merge_job: Option<String>,
}

pub fn run(c: BatchCommand) -> Result<ExitCode> {
    match c {
        BatchCommand::Slurm(a) => slurm_run(a),
    }
}

/// An input argument the jobs need absolute (they may start elsewhere): its path as
/// parsed, and what it is.
type Input = (PathBuf, &'static str);

/// What the batch sets itself on every shard's command line: a placeholder `--out` (the
/// parts' paths) and `--shard` (the task's index).
const BATCH_SET: [&str; 4] = ["--out", "gonio-batch-part", "--shard", "1/1"];

/// Recognise the sharded command by parsing it with gonio's own command line (`args`
/// without the program name), and the input argument to make absolute (a dataset, a family
/// spec). Refuses commands that cannot be sharded, clap's errors, and the options the
/// batch sets itself (`--out`, `--shard`, `--force`, `acquire --resume`, `compress --state`).
fn sharded_kind(args: &[String]) -> Result<(ShardedKind, Option<Input>), String> {
    // The batch's own `--out` and `--shard` are appended; when that fails, the command is
    // parsed without them (one or both were given by the user, or the command has none).
    let parse = |with_out: bool, with_shard: bool| {
        let extra = BATCH_SET
            .chunks(2)
            .zip([with_out, with_shard])
            .filter(|(_, on)| *on)
            .flat_map(|(kv, _)| kv.iter().copied());
        Cli::try_parse_from(
            ["gonio"]
                .into_iter()
                .chain(args.iter().map(String::as_str))
                .chain(extra),
        )
        .map(|cli| (cli.command, with_out, with_shard))
    };
    let mut clap_error = String::new();
    let (command, batch_out, batch_shard) = parse(true, true)
        .or_else(|e| {
            clap_error = format!(
                "`{}` does not parse as a gonio command: {}",
                args.join(" "),
                e.render().to_string().trim_start_matches("error: ").trim_end()
            );
            parse(true, false)
                .or_else(|_| parse(false, true))
                .or_else(|_| parse(false, false))
        })
        .map_err(|_| clap_error.clone())?;
    // (kind, whether the user's command sets --out, --shard, --force; the input argument).
    // Without the batch's `--out`, a user's `--out` is the one parsed (it is required, or
    // acquire's default, which conflicts only with `--resume`, refused below).
    let (kind, out, shard, force, input) = match &command {
        Gonio::Sim(SimCommand::Btf(b)) => (ShardedKind::SimBtf, b.out.is_some(), b.shard.is_some(), b.force, None),
        Gonio::Acquire(a) => {
            if a.resume.is_some() {
                return Err("`acquire --resume` continues one dataset; give the acquisition's own options".into());
            }
            (ShardedKind::Acquire, true, a.shard.is_some(), a.force, None)
        }
        Gonio::Dataset(DatasetCommand::Generate(g)) => (
            ShardedKind::DatasetGenerate,
            true,
            g.shard.is_some(),
            g.force,
            Some((g.spec.clone(), "family spec")),
        ),
        Gonio::Compress(c) => {
            let kind = match c.method.map(|m| shard_kind(m, c)) {
                Some(Shard::Views) => ShardedKind::CompressPvmf,
                Some(Shard::Passes(passes)) => ShardedKind::CompressRsvd { passes },
                Some(Shard::No) | None => {
                    return Err(
                        "`compress` is sharded for --method pvmf (by views), pca, dfmf and local-pca (by passes over the views)"
                            .into(),
                    )
                }
            };
            if c.state.is_some() {
                return Err("`--state` is set by the batch for every round after the first".into());
            }
            (kind, true, c.shard.is_some(), false, Some((c.dataset.clone(), "dataset")))
        }
        _ => {
            return Err(format!(
                "`{}` cannot be sharded; give `sim btf …`, `acquire …`, `compress DATASET --method pvmf|pca|dfmf|local-pca …` or `dataset generate SPEC` after --",
                args.join(" ")
            ))
        }
    };
    let own = if out && !batch_out {
        "--out"
    } else if shard && !batch_shard {
        "--shard"
    } else if force {
        "--force"
    } else if !(batch_out && batch_shard) {
        // The batch's options made it fail for another reason: clap's own words.
        return Err(clap_error);
    } else {
        return Ok((kind, input));
    };
    Err(format!(
        "`{own}` is set by the batch for every shard (parts go to --work DIR/parts, the merged result to --out)"
    ))
}

fn slurm_run(a: SlurmArgs) -> Result<ExitCode> {
    let mut command = a.command.clone();
    if command.first().map(String::as_str) == Some("--") {
        command.remove(0);
    }
    let (kind, input) = sharded_kind(&command).map_err(anyhow::Error::msg)?;
    if !(1..=gonio_dataset::shard::MAX_SHARDS).contains(&a.shards) {
        bail!(
            "--shards {}: valid range is 1 ..= {}",
            a.shards,
            gonio_dataset::shard::MAX_SHARDS
        );
    }
    if a.retries > 10 {
        bail!("--retries {}: at most 10", a.retries);
    }
    if let Some(f) = a.merge_fanout {
        if !matches!(kind, ShardedKind::CompressRsvd { .. }) {
            bail!("--merge-fanout builds a tree of `gonio merge --partial` jobs for compress --method pca|dfmf|local-pca only");
        }
        if f < 2 || !a.shards.is_multiple_of(f) || a.shards / f < 2 {
            bail!(
                "--merge-fanout {f} with --shards {}: F must be at least 2, divide the shards and leave at least 2 groups \
                 (e.g. --shards 64 --merge-fanout 8)",
                a.shards
            );
        }
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
    if let Some((input, what)) = input {
        if let Some(arg) = command.iter_mut().skip(1).find(|a| Path::new(a.as_str()) == input) {
            *arg = abs(&input, what)?.display().to_string();
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
        merge_fanout: a.merge_fanout,
    };
    for p in job.dirs() {
        std::fs::create_dir_all(&p).with_context(|| format!("creating {}", p.display()))?;
    }
    let last = kind.rounds() - 1;
    let mut rounds = Vec::with_capacity(kind.rounds());
    for r in 0..=last {
        let mut scripts = vec![
            (job.array_script_path(r), job.array_script(r)),
            (job.merge_script_path(r), job.merge_script(r)),
        ];
        if let Some(g) = job.group_script(r) {
            scripts.push((job.group_script_path(r), g));
        }
        for (path, text) in scripts {
            std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
        }
        rounds.push(Round {
            array_script: job.array_script_path(r),
            group_script: job.merge_fanout.map(|_| job.group_script_path(r)),
            merge_script: job.merge_script_path(r),
            merged: job.merged(r),
            array_job: None,
            group_job: None,
            merge_job: None,
        });
    }
    let mut report = Report {
        shards: a.shards,
        array_script: job.array_script_path(last),
        merge_script: job.merge_script_path(last),
        parts: (1..=a.shards).map(|i| job.part(last, i)).collect(),
        out: job.out.clone(),
        retries: a.retries,
        retry_mode: a.retry_mode,
        array_job: None,
        merge_job: None,
        rounds,
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
        // Round r's array waits for round r − 1's merge (afterok: its state must exist);
        // each merge runs after its array whatever happened (afterany), so a failed shard
        // is named in the merge's log.
        let mut previous: Option<String> = None;
        for round in &mut report.rounds {
            let mut args = vec!["--parsable".to_string()];
            if let Some(m) = &previous {
                args.push(format!("--dependency=afterok:{m}"));
            }
            args.push(round.array_script.display().to_string());
            let array = submit(&args)?;
            // A tree merge: the group merges after the array, the final merge after them
            // (afterany both: a missing part is named by the merge that lacks it).
            let mut before = array.clone();
            if let Some(g) = &round.group_script {
                let groups = submit(&[
                    "--parsable".into(),
                    format!("--dependency=afterany:{array}"),
                    g.display().to_string(),
                ])?;
                round.group_job = Some(groups.clone());
                before = groups;
            }
            let merge = submit(&[
                "--parsable".into(),
                format!("--dependency=afterany:{before}"),
                round.merge_script.display().to_string(),
            ])?;
            previous = Some(merge.clone());
            round.array_job = Some(array);
            round.merge_job = Some(merge);
        }
        let last = report.rounds.last().expect("at least one round");
        report.array_job = last.array_job.clone();
        report.merge_job = last.merge_job.clone();
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        if report.rounds.len() > 1 {
            println!(
                "rounds         {} (one per randomized-SVD pass; each array starts from the previous merge's state)",
                report.rounds.len()
            );
        }
        println!("array script   {}", report.array_script.display());
        println!("merge script   {}", report.merge_script.display());
        println!(
            "parts          {} … {}",
            report.parts[0].display(),
            report.parts[a.shards - 1].display()
        );
        println!("merged result  {}", report.out.display());
        match (&report.array_job, &report.merge_job) {
            (Some(j), Some(m)) => println!("submitted      array job {j}, merge job {m} (afterany:{j})"),
            _ if report.rounds.len() > 1 => println!(
                "submit with    --submit (the {} rounds chain with afterok on each merge)",
                report.rounds.len()
            ),
            _ => println!(
                "submit with    J=$(sbatch --parsable {}) && sbatch --dependency=afterany:$J {}",
                report.array_script.display(),
                report.merge_script.display()
            ),
        }
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kind(s: &str) -> Result<ShardedKind, String> {
        let args: Vec<String> = s.split_whitespace().map(String::from).collect();
        sharded_kind(&args).map(|(k, _)| k)
    }

    #[test]
    fn only_shardable_commands_without_their_own_shard_or_out() {
        assert_eq!(kind("sim btf --size 32"), Ok(ShardedKind::SimBtf));
        assert_eq!(kind("compress ds --method pvmf -c 4"), Ok(ShardedKind::CompressPvmf));
        assert_eq!(kind("compress ds --method=pvmf -c 4"), Ok(ShardedKind::CompressPvmf));
        // 2 + power iterations (compress's default: 2)
        assert_eq!(
            kind("compress ds --method pca -c 4"),
            Ok(ShardedKind::CompressRsvd { passes: 4 })
        );
        assert_eq!(
            kind("compress ds --method dfmf -c 4 --power-iters 0"),
            Ok(ShardedKind::CompressRsvd { passes: 2 })
        );
        assert_eq!(
            kind("compress ds -c 4 --power-iters=1 --method dfmf"),
            Ok(ShardedKind::CompressRsvd { passes: 3 })
        );
        assert_eq!(
            kind("compress /ds --method local-pca -c 2"),
            Ok(ShardedKind::CompressRsvd {
                passes: gonio_btf::compress::local_pca::passes::PASSES
            })
        );
        assert!(kind("compress ds --method pca -c 4 --state s")
            .unwrap_err()
            .contains("--state"));
        assert!(kind("compress ds --method median-cut")
            .unwrap_err()
            .contains("is sharded for --method pvmf"));
        assert!(kind("compress ds --target-psnr 30")
            .unwrap_err()
            .contains("is sharded for"));
        assert!(kind("compress ds --method pca --power-iters x")
            .unwrap_err()
            .contains("does not parse"));
        assert_eq!(kind("acquire --size 32x32"), Ok(ShardedKind::Acquire));
        assert!(kind("acquire --resume d").unwrap_err().contains("--resume"));
        assert_eq!(kind("dataset generate /s.toml"), Ok(ShardedKind::DatasetGenerate));
        assert!(kind("plan --sweep bonn81").unwrap_err().contains("cannot be sharded"));
        assert!(kind("sim btf --bogus").unwrap_err().contains("does not parse"));
        for (cmd, own) in [
            ("sim btf --out x", "--out"),
            ("sim btf --out=x --size 8", "--out"),
            ("sim btf --shard=1/2", "--shard"),
            ("sim btf --force", "--force"),
            ("acquire --out d", "--out"),
            ("acquire --shard 1/2", "--shard"),
            ("acquire --force", "--force"),
            ("compress ds --method pvmf -c 4 --out f.gbtf", "--out"),
            ("compress ds --method pca -c 4 --shard 2/3", "--shard"),
            ("dataset generate s.toml --out f", "--out"),
            ("dataset generate s.toml --shard 1/3", "--shard"),
            ("dataset generate s.toml --force", "--force"),
        ] {
            let e = kind(cmd).unwrap_err();
            assert!(e.starts_with(&format!("`{own}` is set by the batch")), "{cmd}: {e}");
        }
    }

    #[test]
    fn the_input_is_the_parsed_dataset_or_spec() {
        let args = |s: &str| s.split_whitespace().map(String::from).collect::<Vec<_>>();
        let (_, input) = sharded_kind(&args("compress --method pvmf -c 4 rel/ds")).unwrap();
        assert_eq!(input, Some((PathBuf::from("rel/ds"), "dataset")));
        let (_, input) = sharded_kind(&args("dataset generate s.toml")).unwrap();
        assert_eq!(input, Some((PathBuf::from("s.toml"), "family spec")));
        let (_, input) = sharded_kind(&args("sim btf --size 8")).unwrap();
        assert_eq!(input, None);
    }
}
