//! Slurm job arrays for sharded runs (`gonio batch slurm`): one array task per shard
//! (`--shard $SLURM_ARRAY_TASK_ID/N`) and a merge job that depends on the whole array.
//!
//! The merge job depends on the array with `afterany`, not `afterok`: it runs even when a
//! shard failed for good, so the merge's error (which names the missing or incomplete
//! shards) is in its log instead of a merge job pending forever on an unsatisfiable
//! dependency.
//!
//! A failed shard is retried ([`RetryMode`]): by default inside its own allocation (the
//! array task runs the command again, immediately), or by asking Slurm to requeue the task
//! (`scontrol requeue`; on the test's Slurm 22.05 a requeued task became eligible again
//! only ~2 minutes later, see docs/guide/scale.md). Both kinds of retry are bounded by
//! `retries`; `#SBATCH --requeue` also lets Slurm requeue tasks whose node failed.

use std::path::{Path, PathBuf};

/// Which sharded gonio command the array runs (`cli::batch` recognises it from the parsed
/// command line).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ShardedKind {
    /// `gonio sim btf …`: parts are dataset directories.
    SimBtf,
    /// `gonio acquire …` on a simulated rig: parts are dataset directories.
    Acquire,
    /// `gonio compress … --method pvmf`: parts are `.gbtf` files.
    CompressPvmf,
    /// `gonio compress … --method pca|dfmf|local-pca`: a chain of `passes` rounds (one
    /// per pass over the views), each an array of `.gpart` parts and a merge into the state
    /// the next round starts from (`--state`); the last merge writes the file.
    CompressRsvd { passes: usize },
    /// `gonio dataset generate SPEC …`: every shard writes its own members into the one
    /// family directory (disjoint, no lock); the "merge" job checks that all are complete.
    DatasetGenerate,
}

impl ShardedKind {
    fn part_suffix(self) -> &'static str {
        match self {
            ShardedKind::SimBtf | ShardedKind::Acquire | ShardedKind::DatasetGenerate => "",
            ShardedKind::CompressPvmf => ".gbtf",
            ShardedKind::CompressRsvd { .. } => ".gpart",
        }
    }

    /// Rounds of arrays and merges: one, or one per randomized-SVD pass.
    pub fn rounds(self) -> usize {
        match self {
            ShardedKind::CompressRsvd { passes } => passes,
            _ => 1,
        }
    }
}

/// How a failed shard is retried.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum RetryMode {
    /// The array task runs the command again in its allocation (immediate).
    InJob,
    /// The array task asks Slurm to requeue it (`scontrol requeue`); Slurm restarts it
    /// later, possibly on another node.
    Requeue,
}

/// A sharded job as Slurm scripts.
#[derive(Clone, Debug)]
pub struct SlurmJob {
    pub kind: ShardedKind,
    /// The gonio subcommand and its arguments (without `--shard`, `--out`).
    pub args: Vec<String>,
    pub shards: usize,
    /// Absolute work directory: `parts/`, `logs/` and the scripts go there.
    pub work: PathBuf,
    /// Absolute path of the merged output.
    pub out: PathBuf,
    /// The gonio executable the jobs run (absolute).
    pub gonio: PathBuf,
    pub retries: u32,
    pub retry_mode: RetryMode,
    /// `#SBATCH --cpus-per-task` of each shard.
    pub cpus_per_task: usize,
    /// Extra `#SBATCH` lines (e.g. `--partition=debug`, `--time=1:00:00`), one option each.
    pub sbatch_options: Vec<String>,
    /// `.gpart` rounds: merge as a two-level tree, groups of this many shards first (an
    /// array of `gonio merge --partial` tasks), then the groups; `None`: one flat merge.
    pub merge_fanout: Option<usize>,
}

/// Quote a word for bash (single quotes; `'` as `'\''`).
pub fn shell_quote(s: &str) -> String {
    if !s.is_empty()
        && s.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"-_./=:,+@%".contains(&b))
    {
        return s.to_string();
    }
    format!("'{}'", s.replace('\'', r"'\''"))
}

fn q(p: &Path) -> String {
    shell_quote(&p.display().to_string())
}

impl SlurmJob {
    /// The parts directory of round `r` (0-based): `parts/`, or `parts/pass-R/` when
    /// the job has several rounds.
    fn parts_dir(&self, r: usize) -> PathBuf {
        if self.kind.rounds() == 1 {
            self.work.join("parts")
        } else {
            self.work.join("parts").join(format!("pass-{r}"))
        }
    }

    /// Output of shard `i` (1-based) in round `r`; a family's shards all write into `out`.
    pub fn part(&self, r: usize, i: usize) -> PathBuf {
        if self.kind == ShardedKind::DatasetGenerate {
            return self.out.clone();
        }
        self.parts_dir(r).join(format!("part-{i}{}", self.kind.part_suffix()))
    }

    /// What the merge of round `r` writes: the state of the next round, or `out`.
    pub fn merged(&self, r: usize) -> PathBuf {
        if r + 1 == self.kind.rounds() {
            self.out.clone()
        } else {
            self.work.join(format!("state-{r}.gstate"))
        }
    }

    fn suffix(&self, r: usize) -> String {
        if self.kind.rounds() == 1 {
            String::new()
        } else {
            format!("-{r}")
        }
    }

    /// Group `g` (1-based) of round `r` in a tree merge: shards `(g−1)·F + 1 ..= g·F`.
    pub fn group_part(&self, r: usize, g: usize) -> PathBuf {
        self.parts_dir(r).join(format!("group-{g}.gpart"))
    }

    /// Groups of a tree merge (0: a flat merge).
    pub fn groups(&self) -> usize {
        self.merge_fanout.map_or(0, |f| self.shards / f)
    }

    pub fn group_script_path(&self, r: usize) -> PathBuf {
        self.work.join(format!("groups{}.sbatch", self.suffix(r)))
    }

    /// The group merges of round `r` in a tree merge: task `G` joins its `F` shards into
    /// `parts/…/group-G.gpart` (`gonio merge --partial`).
    pub fn group_script(&self, r: usize) -> Option<String> {
        let f = self.merge_fanout?;
        let sfx = self.suffix(r);
        let mut s = self.header(&format!("groups{sfx}"), &format!("group{sfx}-%a.log"));
        s.push_str(&format!(
            "#SBATCH --array=1-{}
",
            self.groups()
        ));
        s.push_str(
            "set -u
",
        );
        s.push_str(
            "G=${SLURM_ARRAY_TASK_ID:?submit this script with sbatch (it is a job array)}
",
        );
        s.push_str(&format!(
            "parts=()
for i in $(seq $(( (G - 1) * {f} + 1 )) $(( G * {f} ))); do parts+=(\"{}/part-$i{}\"); done
",
            self.parts_dir(r).display(),
            self.kind.part_suffix()
        ));
        s.push_str(&format!(
            "exec {} merge --partial \"${{parts[@]}}\" --out \"{}/group-$G.gpart\" --force --json\n",
            q(&self.gonio),
            self.parts_dir(r).display()
        ));
        Some(s)
    }

    pub fn array_script_path(&self, r: usize) -> PathBuf {
        self.work.join(format!("shards{}.sbatch", self.suffix(r)))
    }

    pub fn merge_script_path(&self, r: usize) -> PathBuf {
        self.work.join(format!("merge{}.sbatch", self.suffix(r)))
    }

    /// Directories the scripts need before they run.
    pub fn dirs(&self) -> Vec<PathBuf> {
        let mut d = vec![self.work.join("logs")];
        d.extend((0..self.kind.rounds()).map(|r| self.parts_dir(r)));
        d
    }

    fn header(&self, name: &str, log: &str) -> String {
        let mut s = format!(
            "#!/bin/bash\n# Written by `gonio batch slurm`; submit with sbatch (see docs/guide/scale.md).\n\
             #SBATCH --job-name=gonio-{name}\n#SBATCH --output={}\n#SBATCH --open-mode=append\n",
            self.work.join("logs").join(log).display()
        );
        for o in &self.sbatch_options {
            s.push_str(&format!("#SBATCH {o}\n"));
        }
        s
    }

    /// The job array of round `r`: task `I` runs the command with `--shard I/N --out
    /// parts/part-I` (and, after the first round of a chain, `--state` of the last merge).
    pub fn array_script(&self, r: usize) -> String {
        let n = self.shards;
        let sfx = self.suffix(r);
        let mut s = self.header(&format!("shards{sfx}"), &format!("shard{sfx}-%a.log"));
        s.push_str(&format!(
            "#SBATCH --array=1-{n}\n#SBATCH --requeue\n#SBATCH --cpus-per-task={}\n",
            self.cpus_per_task
        ));
        if r > 0 {
            // A failed earlier merge leaves this round's dependency unsatisfiable: end it.
            s.push_str("#SBATCH --kill-on-invalid-dep=yes\n");
        }
        s.push_str("set -u\n");
        s.push_str("I=${SLURM_ARRAY_TASK_ID:?submit this script with sbatch (it is a job array)}\n");
        s.push_str(&format!(
            "export RAYON_NUM_THREADS=${{SLURM_CPUS_PER_TASK:-{}}}\n",
            self.cpus_per_task
        ));
        let mut cmd: Vec<String> = vec![q(&self.gonio)];
        cmd.extend(self.args.iter().map(|a| shell_quote(a)));
        cmd.push("--shard".into());
        cmd.push(format!("\"$I/{n}\""));
        if r > 0 {
            cmd.push("--state".into());
            cmd.push(q(&self.merged(r - 1)));
        }
        cmd.push("--out".into());
        if self.kind == ShardedKind::DatasetGenerate {
            cmd.push(q(&self.out));
        } else {
            // Inside double quotes so `$I` expands (the CLI refuses work paths that need
            // escaping there).
            cmd.push(format!(
                "\"{}/part-$I{}\"",
                self.parts_dir(r).display(),
                self.kind.part_suffix()
            ));
        }
        if matches!(self.kind, ShardedKind::SimBtf | ShardedKind::Acquire) {
            cmd.push("--force".into());
        }
        s.push_str(&format!("run() {{ {}; }}\n", cmd.join(" ")));
        s.push_str("stamp() { date -u +%Y-%m-%dT%H:%M:%SZ; }\n");
        match self.retry_mode {
            RetryMode::InJob => s.push_str(&format!(
                "rc=0\nfor attempt in $(seq 1 {tries}); do\n  \
                 echo \"gonio shard $I/{n}: attempt $attempt of {tries} at $(stamp) on $(hostname)\"\n  \
                 if run; then echo \"gonio shard $I/{n}: done at $(stamp)\"; exit 0; else rc=$?; fi\n  \
                 echo \"gonio shard $I/{n}: attempt $attempt failed (exit $rc)\"\n\
                 done\nexit $rc\n",
                tries = self.retries + 1
            )),
            RetryMode::Requeue => s.push_str(&format!(
                "restart=${{SLURM_RESTART_COUNT:-0}}\n\
                 echo \"gonio shard $I/{n}: run $((restart + 1)) at $(stamp) on $(hostname)\"\n\
                 if run; then echo \"gonio shard $I/{n}: done at $(stamp)\"; exit 0; else rc=$?; fi\n\
                 if [ \"$restart\" -lt {r} ]; then\n  \
                 echo \"gonio shard $I/{n}: failed (exit $rc); asking Slurm to requeue it\"\n  \
                 scontrol requeue \"${{SLURM_ARRAY_JOB_ID}}_${{SLURM_ARRAY_TASK_ID}}\" && sleep 600\n\
                 fi\n\
                 echo \"gonio shard $I/{n}: failed (exit $rc), no retries left\"\nexit $rc\n",
                r = self.retries
            )),
        }
        s
    }

    /// The merge job of round `r`: every part (or, in a tree merge, every group part), in
    /// shard order, into the round's [`SlurmJob::merged`] output.
    pub fn merge_script(&self, r: usize) -> String {
        let sfx = self.suffix(r);
        let mut s = self.header(&format!("merge{sfx}"), &format!("merge{sfx}.log"));
        s.push_str("set -u\n");
        let mut cmd: Vec<String> = vec!["exec".into(), q(&self.gonio)];
        if self.kind == ShardedKind::DatasetGenerate {
            cmd.extend(["dataset".into(), "check".into(), q(&self.out), "--json".into()]);
        } else {
            cmd.push("merge".into());
            if self.merge_fanout.is_some() {
                cmd.extend((1..=self.groups()).map(|g| q(&self.group_part(r, g))));
            } else {
                cmd.extend((1..=self.shards).map(|i| q(&self.part(r, i))));
            }
            cmd.extend(["--out".into(), q(&self.merged(r)), "--force".into(), "--json".into()]);
        }
        s.push_str(&cmd.join(" "));
        s.push('\n');
        s
    }
}

/// The absolute path of `program` found in `PATH`, if any.
pub fn which(program: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|d| d.join(program))
        .find(|p| p.is_file())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(s: &str) -> Vec<String> {
        s.split_whitespace().map(String::from).collect()
    }

    #[test]
    fn scripts_run_every_shard_and_merge_all_parts() {
        let job = SlurmJob {
            kind: ShardedKind::SimBtf,
            args: args("sim btf --sample it's"),
            shards: 3,
            work: "/w d".into(),
            out: "/o".into(),
            gonio: "/bin/gonio".into(),
            retries: 1,
            retry_mode: RetryMode::InJob,
            cpus_per_task: 2,
            sbatch_options: vec!["--time=10".into()],
            merge_fanout: None,
        };
        let a = job.array_script(0);
        assert!(a.contains("#SBATCH --array=1-3\n"), "{a}");
        assert!(a.contains("#SBATCH --time=10\n"), "{a}");
        assert!(a.contains(r"'it'\''s' --shard "), "{a}");
        assert!(a.contains(r#"--out "/w d/parts/part-$I" --force"#), "{a}");
        assert!(a.contains("seq 1 2"), "{a}");
        let m = job.merge_script(0);
        assert!(
            m.contains("merge '/w d/parts/part-1' '/w d/parts/part-2' '/w d/parts/part-3' --out /o"),
            "{m}"
        );
        let r = SlurmJob {
            kind: ShardedKind::CompressPvmf,
            retry_mode: RetryMode::Requeue,
            ..job
        };
        let a = r.array_script(0);
        assert!(
            a.contains(r#"--out "/w d/parts/part-$I.gbtf""#) && !a.contains("--force"),
            "{a}"
        );
        assert!(a.contains("scontrol requeue"), "{a}");

        // A family: every shard writes into the family directory; the last job checks it.
        let f = SlurmJob {
            kind: ShardedKind::DatasetGenerate,
            args: args("dataset generate /s.toml"),
            ..r
        };
        let a = f.array_script(0);
        assert!(a.contains(r#"/s.toml --shard "$I/3" --out /o"#), "{a}");
        let m = f.merge_script(0);
        assert!(
            m.contains("dataset check /o --json") && !m.contains("gonio merge "),
            "{m}"
        );

        // A randomized SVD: a chain of rounds, each starting from the previous merge.
        let c = SlurmJob {
            kind: ShardedKind::CompressRsvd { passes: 3 },
            args: args("compress /ds --method pca -c 4"),
            ..f
        };
        assert_eq!(c.array_script_path(0), PathBuf::from("/w d/shards-0.sbatch"));
        let a0 = c.array_script(0);
        assert!(
            a0.contains(r#"--shard "$I/3" --out "/w d/parts/pass-0/part-$I.gpart""#) && !a0.contains("--state"),
            "{a0}"
        );
        let a2 = c.array_script(2);
        assert!(
            a2.contains(r#"--state '/w d/state-1.gstate' --out "/w d/parts/pass-2/part-$I.gpart""#)
                && a2.contains("--kill-on-invalid-dep=yes"),
            "{a2}"
        );
        assert!(c.merge_script(1).contains("--out '/w d/state-1.gstate'"));
        assert!(c.merge_script(2).contains("--out /o --force"));
        assert!(c.group_script(0).is_none());

        // A tree merge: 6 shards in groups of 3, then the 2 groups.
        let t = SlurmJob {
            shards: 6,
            merge_fanout: Some(3),
            ..c
        };
        let g = t.group_script(1).unwrap();
        assert!(g.contains("#SBATCH --array=1-2\n"), "{g}");
        assert!(g.contains("seq $(( (G - 1) * 3 + 1 )) $(( G * 3 ))"), "{g}");
        assert!(
            g.contains(r#"merge --partial "${parts[@]}" --out "/w d/parts/pass-1/group-$G.gpart" --force"#),
            "{g}"
        );
        let m = t.merge_script(1);
        assert!(
            m.contains(
                "merge '/w d/parts/pass-1/group-1.gpart' '/w d/parts/pass-1/group-2.gpart' --out '/w d/state-1.gstate'"
            ),
            "{m}"
        );
    }
}
