//! The layering of `src/`, read from the sources (ARCHITECTURE.md, "Invariants").
//!
//! Each top-level module of the crate (a folder or a single file under `src/`) may import
//! only the modules its row of [`ALLOWED`] names; the rows form a DAG, so no folder imports
//! upward and no two folders form a cycle. And `gonio_simulator` appears only where
//! [`SIMULATOR_ALLOWED`] says. Test code (`tests.rs` files, `#[cfg(test)]` modules at the
//! end of a file) is exempt: tests may build a simulated rig anywhere.
//!
//! The check is textual on purpose (like rust-analyzer's tidy tests): it needs no parser,
//! runs in milliseconds and reads the rule in the same words a reviewer would.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// Module → the modules of `src/` it may import (`crate::X`).
const ALLOWED: &[(&str, &[&str])] = &[
    // ground floor
    ("sweep", &[]),
    ("rig", &[]),
    // which part of a job a shard is (`--shard I/N`): a value every heavy job reads
    ("shard", &[]),
    ("develop", &[]),
    // data
    ("plan", &["sweep"]),
    // the Zarr export writes a shard's views (`store/export/zarr.rs`, `--shard I/N`)
    ("store", &["sweep", "shard"]),
    // synthetic BTFs and families of them, written as datasets
    ("synth", &["sweep", "shard", "store"]),
    // drivers and processors: siblings that never import each other
    ("engine", &["plan", "rig", "develop", "store", "sweep"]),
    ("calibrate", &["rig", "develop", "sweep"]),
    ("compress", &["store", "sweep", "shard"]),
    // fitting analytic BRDF models: reads datasets through compress's reader and is
    // measured as a compression method (`compress::evaluate`); nothing imports it but cli
    ("fit", &["compress"]),
    ("synthesize", &["compress", "store", "sweep"]),
    // the viewer reads datasets and compressed files (and renders them)
    ("view", &["compress", "store", "sweep"]),
    // shards of the heavy jobs, their merge, and the scheduler that runs them
    ("merge", &["shard", "compress", "store", "sweep"]),
    ("slurm", &["shard"]),
    // the acquisition session (a shard of it runs some views), then the command line on top
    (
        "session",
        &[
            "engine",
            "calibrate",
            "plan",
            "rig",
            "develop",
            "store",
            "sweep",
            "shard",
        ],
    ),
    (
        "cli",
        &[
            "session",
            "engine",
            "calibrate",
            "compress",
            "fit",
            "plan",
            "rig",
            "develop",
            "store",
            "sweep",
            "synth",
            "synthesize",
            "view",
            "shard",
            "merge",
            "slurm",
        ],
    ),
];

/// Where `gonio_simulator` may be named outside tests: the rig (which backend), the
/// session and the CLI (which sample), `synth` (the truth BTF), and `calibrate/recipe.rs`'s
/// render settings of simulated calibration runs (the one named exception), and `fit`,
/// which fits the material library's analytic models (`gonio_simulator::brdf`, one
/// implementation of each model) and reads no simulator truth.
const SIMULATOR_ALLOWED: &[&str] = &["rig", "session", "cli", "synth", "calibrate/recipe.rs", "fit"];

/// A file's module (`cli`, `rig`, `sweep`, …) and the part of its text that is not tests.
fn module_of(rel: &str) -> &str {
    let first = rel.split('/').next().unwrap_or(rel);
    first.strip_suffix(".rs").unwrap_or(first)
}

fn non_test_part(text: &str) -> &str {
    match text.find("#[cfg(test)]\nmod ") {
        Some(i) => &text[..i],
        None => text,
    }
}

/// Every `crate::X` module a source text names (comments included: a doc link across a
/// forbidden line is a dependency too).
fn crate_refs(text: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let mut rest = text;
    while let Some(i) = rest.find("crate::") {
        let before = rest[..i].chars().last();
        rest = &rest[i + "crate::".len()..];
        // `gonio_crate::` or `my_crate::` are not ours
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
            continue;
        }
        let name: String = rest.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
        if !name.is_empty() {
            out.insert(name);
        }
    }
    out
}

/// The violations in one file (`rel` relative to `src/`).
fn check_file(rel: &str, text: &str) -> Vec<String> {
    let allowed: BTreeMap<&str, &[&str]> = ALLOWED.iter().copied().collect();
    let module = module_of(rel);
    // lib.rs and main.rs declare modules; this file quotes forbidden paths as test data.
    if matches!(module, "lib" | "main" | "layering") || rel.ends_with("/tests.rs") {
        return Vec::new();
    }
    let code = non_test_part(text);
    let mut out = Vec::new();
    let Some(ok) = allowed.get(module) else {
        return vec![format!(
            "{rel}: module `{module}` has no row in layering::ALLOWED: add one"
        )];
    };
    for r in crate_refs(code) {
        if r != module && !ok.contains(&r.as_str()) {
            out.push(format!(
                "{rel}: `{module}` imports `crate::{r}`, which its floor may not"
            ));
        }
    }
    let sim_ok = SIMULATOR_ALLOWED.iter().any(|a| *a == module || *a == rel);
    if !sim_ok && code.contains("gonio_simulator") {
        out.push(format!(
            "{rel}: names gonio_simulator outside rig/, session/, cli/ and synth/"
        ));
    }
    out
}

fn rs_files(dir: &Path, base: &Path, out: &mut Vec<(String, String)>) {
    let mut entries: Vec<_> = std::fs::read_dir(dir).unwrap().flatten().collect();
    entries.sort_by_key(|e| e.path());
    for e in entries {
        let p = e.path();
        if p.is_dir() {
            rs_files(&p, base, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            let rel = p.strip_prefix(base).unwrap().to_string_lossy().replace('\\', "/");
            out.push((rel, std::fs::read_to_string(&p).unwrap()));
        }
    }
}

#[test]
fn the_allowed_imports_form_a_dag() {
    let allowed: BTreeMap<&str, &[&str]> = ALLOWED.iter().copied().collect();
    // Kahn: repeatedly remove modules whose allowed imports are all removed.
    let mut left: BTreeSet<&str> = allowed.keys().copied().collect();
    while !left.is_empty() {
        let ready: Vec<&str> = left
            .iter()
            .copied()
            .filter(|m| allowed[m].iter().all(|d| !left.contains(d)))
            .collect();
        assert!(!ready.is_empty(), "a cycle among {left:?}");
        for m in ready {
            left.remove(m);
        }
    }
    for (m, deps) in ALLOWED {
        for d in *deps {
            assert!(allowed.contains_key(d), "{m} allows unknown module {d}");
        }
    }
}

#[test]
fn no_file_imports_across_a_forbidden_line() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rs_files(&src, &src, &mut files);
    assert!(files.len() > 50, "read the sources ({} files)", files.len());
    let violations: Vec<String> = files.iter().flat_map(|(rel, text)| check_file(rel, text)).collect();
    assert!(violations.is_empty(), "layering violations:\n{}", violations.join("\n"));
}

/// The checker itself catches what it must (a test that can fail).
#[test]
fn the_checker_sees_forbidden_imports() {
    assert!(check_file("engine/mod.rs", "use crate::calibrate::apply::X;").len() == 1);
    assert!(check_file("develop/raw.rs", "use crate::store::Dataset;").len() == 1);
    assert!(check_file("compress/pca.rs", "use gonio_simulator::SimWorld;").len() == 1);
    assert!(
        check_file("newfolder/x.rs", "").len() == 1,
        "unknown modules must be placed"
    );
    // allowed: same module, a lower floor, test code, other crates' `crate::`-like words
    assert!(check_file("engine/mod.rs", "use crate::engine::metrics; use crate::rig::Rig;").is_empty());
    assert!(check_file(
        "engine/mod.rs",
        "x\n#[cfg(test)]\nmod tests { use crate::calibrate::X; }"
    )
    .is_empty());
    assert!(check_file("develop/tests.rs", "use crate::calibrate::X;").is_empty());
    assert!(check_file("calibrate/recipe.rs", "gonio_simulator::SimOptions").is_empty());
    assert!(check_file("plan/order.rs", "my_crate::engine").is_empty());
}
