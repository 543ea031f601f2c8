//! The layering of gonio's rooms, read from the sources (ARCHITECTURE.md, "Invariants").
//!
//! A *room* is a top-level module of one of gonio's crates (a folder or a single file under
//! `dataset/src`, `acquire/src`, `btf/src` or `src`); room names are unique across the
//! crates. A folder of `src` with its own `main.rs` is a binary of its own ([`BIN_ROOMS`]:
//! `bench/`, the `gonio-bench` binary): one room at the top, whose `main.rs` dispatches
//! like a `mod.rs` and whose `crate::` names its own modules. Between crates, Cargo
//! enforces the direction (a wrong `use` does not compile). Inside a crate, and for the
//! finer rules the crates do not express, this test does:
//!
//! 1. each room imports only the rooms of its row in [`ALLOWED`], whichever way it names
//!    them: `crate::X`, `gonio_dataset::X` (any gonio crate), grouped imports
//!    (`crate::{X::a, Y}`), and `super::` chains that climb out of the room; the rows form
//!    a DAG;
//! 2. `gonio_simulator` is named only where [`SIMULATOR_ALLOWED`] says;
//! 3. inside every folder, the files that siblings import are the folder's named shared
//!    files ([`FOLDERS`]): a file imports from its siblings only their shared files, and
//!    every folder has a row.
//!
//! Test code is exempt: `tests.rs` files, files a `#[cfg(test)] mod x;` declares, and every
//! item under `#[cfg(test)]` wherever it stands in a file (matched brace by brace, with
//! strings, characters and comments skipped). Comments are otherwise read: a doc link across
//! a forbidden line is a dependency too.
//!
//! The check is textual on purpose (like rust-analyzer's tidy tests): it needs no parser,
//! runs in milliseconds and reads the rule in the same words a reviewer would.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// gonio's crates whose rooms this test reads: (folder, crate name in paths).
const CRATES: &[(&str, &str)] = &[
    ("dataset", "gonio_dataset"),
    ("acquire", "gonio_acquire"),
    ("btf", "gonio_btf"),
    (".", "gonio"),
];

/// Room → the rooms it may import.
const ALLOWED: &[(&str, &[&str])] = &[
    // gonio-dataset: the on-disk contract
    ("sweep", &[]),
    // which part of a job a shard is (`--shard I/N`): a value every heavy job reads
    ("shard", &[]),
    // the Zarr export writes a shard's views (`store/export/zarr.rs`, `--shard I/N`)
    ("store", &["sweep", "shard"]),
    // gonio-acquire: the ground floor (hardware step, per-frame chain) imports no room
    ("rig", &[]),
    ("develop", &[]),
    ("plan", &["sweep"]),
    // drivers and processors: siblings that never import each other
    ("engine", &["plan", "rig", "develop", "store", "sweep"]),
    ("calibrate", &["rig", "develop", "sweep"]),
    // the acquisition session (a shard of it runs some views)
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
    // gonio-btf
    ("compress", &["store", "sweep", "shard"]),
    // fitting analytic BRDF models: reads datasets through compress's reader and is
    // measured as a compression method (`compress::evaluate`)
    ("fit", &["compress", "sweep"]),
    ("synthesize", &["compress", "store", "sweep"]),
    // a fitted model written for renderers: reads `.gbtf` files and the fit's conventions
    ("export", &["compress", "fit", "store", "sweep"]),
    // gonio (the binary's rooms): synthetic BTFs and families of them, written as datasets
    ("synth", &["sweep", "shard", "store"]),
    // the viewer reads datasets and compressed files (and renders them)
    ("view", &["compress", "store", "sweep"]),
    // shards of the heavy jobs, their merge, and the scheduler that runs them
    ("merge", &["shard", "compress", "store", "sweep"]),
    ("slurm", &["shard"]),
    (
        "cli",
        &[
            "session",
            "engine",
            "calibrate",
            "compress",
            "fit",
            "export",
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
    // the benchmarks (`gonio-bench`, its own binary): they drive the commands' code through
    // the library (`gonio::cli::bench`) and every floor below; nothing imports them
    (
        "bench",
        &[
            "cli",
            "session",
            "engine",
            "calibrate",
            "compress",
            "fit",
            "export",
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

/// Rooms that are binaries of their own (a folder of `src` with a `main.rs`): inside them
/// `crate::` names the binary's own modules, and `main.rs` dispatches like a `mod.rs`.
const BIN_ROOMS: &[&str] = &["bench"];

/// Where `gonio_simulator` may be named outside tests: the rig (which backend), the
/// session, the CLI and the benchmarks (which sample), `synth` (the truth BTF), and
/// `calibrate/recipe.rs`'s render settings of simulated calibration runs (the one named
/// exception). The material library is its own crate (`gonio_brdf`), so fitting and
/// compression never name the simulator.
const SIMULATOR_ALLOWED: &[&str] = &["rig", "session", "cli", "bench", "synth", "calibrate/recipe.rs"];

/// Every folder of every room (path relative to its crate's `src/`) → the files its siblings
/// may import ("shared files": the folder's ground floor and its registries). `mod.rs`
/// dispatches and may import any sibling; a folder's main type may live in it.
const FOLDERS: &[(&str, &[&str])] = &[
    (
        "store",
        &[
            "atomic",
            "error",
            "export",
            "journal",
            "manifest",
            "provenance",
            "reference",
        ],
    ),
    ("store/export", &["entry", "npy", "ubo2003"]),
    ("rig", &["backends", "capture"]),
    ("develop", &[]),
    ("plan", &["order", "sparse"]),
    ("engine", &[]),
    (
        "calibrate",
        &[
            "apply",
            "light_geometry",
            "mechanical",
            "offset_fit",
            "radiometric",
            "recipe",
            "rig_geometry",
            "uncertainty",
            "white",
        ],
    ),
    ("session", &[]),
    (
        "compress",
        &[
            // the ground floor every method shares
            "params",
            "linalg",
            "abrdf",
            "data",
            "container",
            "codec",
            "error",
            "exact",
            "rsvd",
            // the readers, the registry of methods and the dispatch through it
            "registry",
            "factor",
            "interp",
            "metrics",
            // methods whose factors another method or the sharded passes reuse
            "pca",
            "dfmf",
            "btf_ubo2014",
            "local_pca",
            "cmf",
            "homomorphic",
            "median_cut",
            "nd",
            "pvmf",
            "svbrdf",
            "gltf",
            "svd_j",
        ],
    ),
    ("compress/local_pca", &[]),
    ("fit", &["data", "lm", "models"]),
    ("export", &["average", "texture"]),
    ("synthesize", &["features", "fft", "output", "tsvq"]),
    ("synth", &["dataset"]),
    ("synth/family", &[]),
    ("view", &["abrdf_cache", "gpu", "monitor", "params", "render", "source"]),
    ("view/assets", &[]),
    (
        "cli",
        &[
            "common",
            "svg_plot",
            // `bench.rs` re-exports what the benchmarks (`src/bench/`) use of these
            "acquire",
            "compress",
            "fit",
            "synthesize",
            "sim",
            "sim_btf",
            "serve_stage",
            // `sim serve-light` (sim registers it; it shares serve-stage's serving loop)
            "serve_light",
            // `batch slurm` matches on the parsed commands it shards
            "dataset",
            // sparse acquisition: `sparse` holds the flags, `--prior` resolution and the
            // summary that `plan` and `acquire` share (the design itself is
            // `gonio_acquire::plan::sparse`); `complete` reads datasets through `prior`'s
            // helpers, and `bench.rs` re-exports both for `gonio bench sparse`
            "sparse",
            "prior",
            "complete",
        ],
    ),
    // one module per benchmark; `main.rs` dispatches, and no benchmark imports another
    ("bench", &[]),
    // `sparse.rs`'s own experiments (the kriging of the span's residual)
    ("bench/sparse", &[]),
];

/// The crate's root files: they declare modules and re-export, and this file quotes
/// forbidden paths as test data.
const ROOT_FILES: &[&str] = &["lib.rs", "main.rs", "layering.rs"];

/// The module paths of a crate's files (`store`, `store/export`, `store/export/entry`).
fn module_set<'a>(rels: impl Iterator<Item = &'a str>) -> BTreeSet<String> {
    rels.map(|r| module_path(r).join("/")).collect()
}

/// One source file of a gonio crate.
struct Source {
    /// Crate folder (`dataset`, …, `.`).
    krate: &'static str,
    /// Path relative to the crate's `src/`, `/`-separated.
    rel: String,
    text: String,
}

// ---------------------------------------------------------------------------------------
// Reading a file: what is test code, what is a path

/// Byte ranges of `text` that are code (outside strings, characters and comments), as a
/// mask: `code[i]` is true where byte `i` is code.
fn code_mask(text: &str) -> Vec<bool> {
    let b = text.as_bytes();
    let mut mask = vec![true; b.len()];
    let mut i = 0;
    while i < b.len() {
        let start = i;
        if b[i..].starts_with(b"//") {
            while i < b.len() && b[i] != b'\n' {
                i += 1;
            }
        } else if b[i..].starts_with(b"/*") {
            let mut depth = 0;
            while i < b.len() {
                if b[i..].starts_with(b"/*") {
                    depth += 1;
                    i += 2;
                } else if b[i..].starts_with(b"*/") {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    i += 1;
                }
            }
        } else if b[i] == b'r' && (b.get(i + 1) == Some(&b'"') || b.get(i + 1) == Some(&b'#')) && !ident_before(b, i) {
            // raw string r"…" or r#"…"#
            let mut j = i + 1;
            let mut hashes = 0;
            while b.get(j) == Some(&b'#') {
                hashes += 1;
                j += 1;
            }
            if b.get(j) != Some(&b'"') {
                i += 1;
                continue;
            }
            j += 1;
            let close: Vec<u8> = std::iter::once(b'"').chain(std::iter::repeat_n(b'#', hashes)).collect();
            while j < b.len() && !b[j..].starts_with(&close) {
                j += 1;
            }
            i = (j + close.len()).min(b.len());
        } else if b[i] == b'"' {
            i += 1;
            while i < b.len() && b[i] != b'"' {
                if b[i] == b'\\' {
                    i += 1;
                }
                i += 1;
            }
            i = (i + 1).min(b.len());
        } else if b[i] == b'\'' {
            // a character literal ('x', '\n', '\u{..}') or a lifetime ('a)
            let lit_end = if b.get(i + 1) == Some(&b'\\') {
                b[i + 2..].iter().position(|&c| c == b'\'').map(|p| i + 2 + p + 1)
            } else if let Some(c) = text[i + 1..].chars().next() {
                let after = i + 1 + c.len_utf8();
                (b.get(after) == Some(&b'\'')).then_some(after + 1)
            } else {
                None
            };
            match lit_end {
                Some(e) => i = e,
                None => {
                    i += 1;
                    continue;
                }
            }
        } else {
            i += 1;
            continue;
        }
        for m in &mut mask[start..i.min(b.len())] {
            *m = false;
        }
    }
    mask
}

fn ident_before(b: &[u8], i: usize) -> bool {
    i > 0 && (b[i - 1].is_ascii_alphanumeric() || b[i - 1] == b'_')
}

/// `text` without its test code: every item under `#[cfg(test)]` (a `mod x { … }` to its
/// matching brace, a `mod x;` declaration, a `use`, a `fn`, an `impl`), and the names of
/// the test modules declared as files (`#[cfg(test)] mod x;`).
fn strip_test_code(text: &str) -> (String, Vec<String>) {
    let mask = code_mask(text);
    let b = text.as_bytes();
    let mut keep = vec![true; b.len()];
    let mut test_files = Vec::new();
    let mut from = 0;
    while let Some(p) = text[from..].find("#[cfg(test)]") {
        let at = from + p;
        from = at + 1;
        if !mask[at] {
            continue;
        }
        // The item ends at its first code `;` before any `{`, or at the brace matching
        // its first code `{`.
        let mut i = at + "#[cfg(test)]".len();
        let mut end = b.len();
        while i < b.len() {
            if mask[i] && b[i] == b';' {
                end = i + 1;
                break;
            }
            if mask[i] && b[i] == b'{' {
                let mut depth = 0usize;
                while i < b.len() {
                    if mask[i] && b[i] == b'{' {
                        depth += 1;
                    } else if mask[i] && b[i] == b'}' {
                        depth -= 1;
                        if depth == 0 {
                            break;
                        }
                    }
                    i += 1;
                }
                end = (i + 1).min(b.len());
                break;
            }
            i += 1;
        }
        let item = &text[at..end];
        if item.trim_end().ends_with(';') {
            if let Some(m) = item.split_whitespace().skip_while(|w| *w != "mod").nth(1) {
                test_files.push(m.trim_end_matches(';').to_string());
            }
        }
        for k in &mut keep[at..end] {
            *k = false;
        }
        from = end.max(from);
    }
    let kept: Vec<u8> = b.iter().zip(&keep).filter(|(_, k)| **k).map(|(c, _)| *c).collect();
    (String::from_utf8_lossy(&kept).into_owned(), test_files)
}

/// The identifiers a path continues with after `prefix::`: one name, or the first name
/// of each element of a group `{a::b, c, d::{e}}`.
fn heads_after(rest: &str) -> Vec<String> {
    let ident = |s: &str| -> String {
        s.trim_start()
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect()
    };
    let Some(group) = rest.strip_prefix('{') else {
        return vec![ident(rest)];
    };
    let mut out = Vec::new();
    let mut depth = 0usize;
    let mut start = 0;
    for (i, c) in group.char_indices() {
        match c {
            '{' => depth += 1,
            '}' if depth == 0 => {
                out.push(ident(&group[start..i]));
                break;
            }
            '}' => depth -= 1,
            ',' if depth == 0 => {
                out.push(ident(&group[start..i]));
                start = i + 1;
            }
            _ => {}
        }
    }
    out.into_iter().filter(|s| !s.is_empty() && s != "self").collect()
}

/// The module path of a file: `plan/isotropic.rs` → [plan, isotropic], `plan/mod.rs` →
/// [plan], `sweep.rs` → [sweep], a binary room's `bench/main.rs` → [bench].
fn module_path(rel: &str) -> Vec<String> {
    let mut parts: Vec<String> = rel.trim_end_matches(".rs").split('/').map(String::from).collect();
    if parts.last().is_some_and(|p| p == "mod") || is_bin_main(rel) {
        parts.pop();
    }
    parts
}

/// The `main.rs` of a binary room ([`BIN_ROOMS`]): its root, which dispatches like a `mod.rs`.
fn is_bin_main(rel: &str) -> bool {
    BIN_ROOMS.iter().any(|r| rel.strip_prefix(r) == Some("/main.rs"))
}

/// What a file's code names: (room, module path inside the room) for every `crate::`,
/// `gonio_*::` and climbing `super::` path. Paths inside the file's own room are returned
/// too (the room is the file's), for the folder rule. In a binary room ([`BIN_ROOMS`]),
/// `crate::` is the binary's root, the room itself.
fn references(rel: &str, code: &str, crate_names: &[&str]) -> BTreeSet<(String, String)> {
    let me = module_path(rel);
    let mut out = BTreeSet::new();
    let bytes = code.as_bytes();
    let mut i = 0;
    while i < code.len() {
        if !code.is_char_boundary(i) || ident_before(bytes, i) {
            i += 1;
            continue;
        }
        let rest = &code[i..];
        // `crate::` / `gonio_x::` → absolute; `super::super::…` → relative to `me`
        let absolute = if let Some(r) = rest.strip_prefix("crate::") {
            Some(r)
        } else {
            crate_names
                .iter()
                .find_map(|c| rest.strip_prefix(c).and_then(|r| r.strip_prefix("::")))
        };
        let own_crate = rest.starts_with("crate::") && BIN_ROOMS.contains(&me[0].as_str());
        let (base, after): (Vec<String>, &str) = if let (Some(r), true) = (absolute, own_crate) {
            (me[..1].to_vec(), r)
        } else if let Some(r) = absolute {
            (Vec::new(), r)
        } else if rest.starts_with("super::") {
            let mut r = rest;
            let mut up = 0;
            while let Some(x) = r.strip_prefix("super::") {
                r = x;
                up += 1;
            }
            // `super` of a file's module: its parent; of an item inside `mod.rs`, the same.
            let keep = me.len().saturating_sub(up);
            (me[..keep].to_vec(), r)
        } else {
            i += 1;
            continue;
        };
        for head in heads_after(after) {
            // (room, path inside it): `crate::room::x…` → (room, x); a climbing `super::`
            // path from base [room, a, …] → (room, a/…/head).
            let (room, inner) = match base.split_first() {
                None => {
                    let tail = after.strip_prefix(&head).and_then(|t| t.strip_prefix("::"));
                    let second = tail.and_then(|t| heads_after(t).into_iter().next()).unwrap_or_default();
                    (head, second)
                }
                Some((room, within)) => {
                    let mut inner = within.to_vec();
                    inner.push(head);
                    (room.clone(), inner.join("/"))
                }
            };
            out.insert((room, inner));
        }
        i += 1;
    }
    out
}

// ---------------------------------------------------------------------------------------
// The rules

/// The violations in one file (`rel` relative to its crate's `src/`).
fn check_file(rel: &str, text: &str, test_files: &BTreeSet<String>, modules: &BTreeSet<String>) -> Vec<String> {
    let allowed: BTreeMap<&str, &[&str]> = ALLOWED.iter().copied().collect();
    let rooms: BTreeSet<&str> = allowed.keys().copied().collect();
    let crate_names: Vec<&str> = CRATES.iter().map(|c| c.1).collect();
    if ROOT_FILES.contains(&rel) || rel.ends_with("/tests.rs") || test_files.contains(rel) {
        return Vec::new();
    }
    let me = module_path(rel);
    let room = me[0].as_str();
    let Some(ok) = allowed.get(room) else {
        return vec![format!("{rel}: room `{room}` has no row in layering::ALLOWED: add one")];
    };
    let (code, _) = strip_test_code(text);
    let mut out = Vec::new();
    for (r, inner) in references(rel, &code, &crate_names) {
        if r == room {
            out.extend(check_sibling(rel, &me, &inner, modules));
        } else if rooms.contains(r.as_str()) && !ok.contains(&r.as_str()) {
            out.push(format!("{rel}: room `{room}` imports `{r}`, which its floor may not"));
        }
    }
    let sim_ok = SIMULATOR_ALLOWED.iter().any(|a| *a == room || *a == rel);
    if !sim_ok && code.contains("gonio_simulator") {
        out.push(format!(
            "{rel}: names gonio_simulator outside {}",
            SIMULATOR_ALLOWED.join(", ")
        ));
    }
    out
}

/// The folder rule for one reference from file `me` to `inner` inside its own room.
fn check_sibling(rel: &str, me: &[String], inner: &str, modules: &BTreeSet<String>) -> Vec<String> {
    let folders: BTreeMap<&str, &[&str]> = FOLDERS.iter().copied().collect();
    // The referenced file: the first segment of `inner` that is not a folder on the way.
    let segs: Vec<&str> = inner.split('/').filter(|s| !s.is_empty()).collect();
    let mut folder = me[0].clone();
    let mut target = None;
    for (k, s) in segs.iter().enumerate() {
        let sub = format!("{folder}/{s}");
        if k + 1 < segs.len() && folders.contains_key(sub.as_str()) {
            folder = sub;
        } else {
            target = Some(s.to_string());
            break;
        }
    }
    let is_mod_rs = rel.ends_with("mod.rs") || !rel.contains('/') || is_bin_main(rel);
    // Only a sibling *file or folder* counts; other names are items of the folder's mod.rs.
    let Some(file) = target.filter(|f| modules.contains(&format!("{folder}/{f}"))) else {
        return Vec::new();
    };
    let my_file = me.last().map(String::as_str).unwrap_or("");
    let my_folder = me[..me.len().saturating_sub(1)].join("/");
    // mod.rs dispatches; a file naming itself or its own children is inside its own module
    if is_mod_rs || file == my_file || folder != my_folder {
        return Vec::new();
    }
    match folders.get(folder.as_str()) {
        Some(shared) if shared.contains(&file.as_str()) => Vec::new(),
        Some(_) => vec![format!(
            "{rel}: imports its sibling `{folder}/{file}`, which layering::FOLDERS does not name as shared"
        )],
        None => Vec::new(),
    }
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

/// Every source file of gonio's crates.
fn sources() -> Vec<Source> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut out = Vec::new();
    for (krate, _) in CRATES {
        let src = root.join(krate).join("src");
        let mut files = Vec::new();
        rs_files(&src, &src, &mut files);
        out.extend(files.into_iter().map(|(rel, text)| Source { krate, rel, text }));
    }
    out
}

/// The files that `#[cfg(test)] mod x;` declarations make test code, per crate.
fn test_files(sources: &[Source]) -> BTreeMap<&'static str, BTreeSet<String>> {
    let mut out: BTreeMap<&str, BTreeSet<String>> = BTreeMap::new();
    for s in sources {
        let (_, mods) = strip_test_code(&s.text);
        let dir = Path::new(&s.rel)
            .parent()
            .map(|p| p.to_string_lossy().into_owned())
            .unwrap_or_default();
        let own = if s.rel.ends_with("mod.rs") || ROOT_FILES.contains(&s.rel.as_str()) || is_bin_main(&s.rel) {
            dir.clone()
        } else {
            format!("{dir}/{}", s.rel.trim_end_matches(".rs").rsplit('/').next().unwrap())
                .trim_start_matches('/')
                .to_string()
        };
        for m in mods {
            let base = if own.is_empty() {
                m.clone()
            } else {
                format!("{own}/{m}")
            };
            let e = out.entry(s.krate).or_default();
            e.insert(format!("{base}.rs"));
            e.insert(format!("{base}/mod.rs"));
        }
    }
    out
}

#[test]
fn the_allowed_imports_form_a_dag() {
    let allowed: BTreeMap<&str, &[&str]> = ALLOWED.iter().copied().collect();
    // Kahn: repeatedly remove rooms whose allowed imports are all removed.
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
            assert!(allowed.contains_key(d), "{m} allows unknown room {d}");
        }
    }
}

#[test]
fn no_file_imports_across_a_forbidden_line() {
    let sources = sources();
    assert!(sources.len() > 100, "read the sources ({} files)", sources.len());
    let tests = test_files(&sources);
    let empty = BTreeSet::new();
    let modules: BTreeMap<&str, BTreeSet<String>> = CRATES
        .iter()
        .map(|(k, _)| {
            (
                *k,
                module_set(sources.iter().filter(|s| s.krate == *k).map(|s| s.rel.as_str())),
            )
        })
        .collect();
    let violations: Vec<String> = sources
        .iter()
        .flat_map(|s| {
            check_file(&s.rel, &s.text, tests.get(s.krate).unwrap_or(&empty), &modules[s.krate])
                .into_iter()
                .map(move |v| format!("{}/src/{v}", s.krate))
        })
        .collect();
    assert!(violations.is_empty(), "layering violations:\n{}", violations.join("\n"));
}

/// Every folder of every room has a row in [`FOLDERS`], and every row names a folder.
#[test]
fn every_folder_has_a_row() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut found = BTreeSet::new();
    fn walk(dir: &Path, base: &Path, out: &mut BTreeSet<String>) {
        for e in std::fs::read_dir(dir).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                out.insert(p.strip_prefix(base).unwrap().to_string_lossy().replace('\\', "/"));
                walk(&p, base, out);
            }
        }
    }
    for (krate, _) in CRATES {
        let src = root.join(krate).join("src");
        walk(&src, &src, &mut found);
    }
    let rows: BTreeSet<String> = FOLDERS.iter().map(|f| f.0.to_string()).collect();
    let missing: Vec<&String> = found.difference(&rows).collect();
    let stale: Vec<&String> = rows.difference(&found).collect();
    assert!(
        missing.is_empty(),
        "folders without a row in layering::FOLDERS: {missing:?}"
    );
    assert!(
        stale.is_empty(),
        "rows of layering::FOLDERS naming no folder: {stale:?}"
    );
}

/// The checker itself catches what it must (a test that can fail), including the three
/// blind spots of the former guard: an import after a `#[cfg(test)] mod tests;` near the
/// top of a file, a grouped import, and a `super::super::` path.
#[test]
fn the_checker_sees_forbidden_imports() {
    let none = BTreeSet::new();
    let modules = module_set(
        [
            "compress/pca.rs",
            "compress/target.rs",
            "compress/linalg.rs",
            "compress/params.rs",
            "synthesize/quilting.rs",
            "synthesize/wei_levoy.rs",
            "plan/order.rs",
            "plan/sparse.rs",
            "plan/fly.rs",
            "bench/main.rs",
            "bench/plan.rs",
            "bench/render.rs",
            "bench/sim.rs",
        ]
        .into_iter(),
    );
    let bad = |rel: &str, text: &str| check_file(rel, text, &none, &modules);
    assert_eq!(bad("engine/mod.rs", "use crate::calibrate::apply::X;").len(), 1);
    assert_eq!(bad("develop/raw.rs", "use gonio_dataset::store::Dataset;").len(), 1);
    assert_eq!(bad("compress/pca.rs", "use gonio_simulator::SimWorld;").len(), 1);
    assert_eq!(bad("newfolder/x.rs", "").len(), 1, "unknown rooms must be placed");
    // blind spot 1: production code after a test module declared near the top
    assert_eq!(
        bad(
            "store/mod.rs",
            "#[cfg(test)]\nmod tests;\n\nuse crate::session::Session;\n"
        )
        .len(),
        1
    );
    assert_eq!(
        bad(
            "store/mod.rs",
            "#[cfg(test)]\nmod tests {\n    fn f() { let s = \"}\"; }\n}\nuse gonio::session::Session;\n"
        )
        .len(),
        1,
        "a brace in a string does not end the test module early"
    );
    // blind spot 2: grouped imports
    assert_eq!(
        bad("plan/mod.rs", "use crate::{cli::Cli, sweep::Sweep as _S};").len(),
        1
    );
    assert_eq!(
        bad("plan/mod.rs", "use gonio::{sweep::Sweep, cli::{Cli, Command}};").len(),
        1
    );
    // blind spot 3: super:: chains climbing out of the room
    assert_eq!(bad("plan/isotropic.rs", "use super::super::cli::Cli;").len(), 1);
    assert_eq!(bad("plan/mod.rs", "use super::cli::Cli;").len(), 1);
    // the folder rule: a sibling that is not named as shared
    assert_eq!(bad("compress/pca.rs", "use super::target::X;").len(), 1);
    assert_eq!(
        bad("synthesize/quilting.rs", "use crate::synthesize::wei_levoy::X;").len(),
        1
    );

    // allowed: same room, a lower floor, test code, other crates' `crate::`-like words
    assert!(bad("engine/mod.rs", "use crate::engine::metrics; use crate::rig::Rig;").is_empty());
    assert!(bad(
        "engine/mod.rs",
        "x\n#[cfg(test)]\nmod tests { use crate::calibrate::X; }"
    )
    .is_empty());
    assert!(bad("engine/mod.rs", "#[cfg(test)]\nuse crate::calibrate::X;\nfn f() {}").is_empty());
    assert!(bad("develop/tests.rs", "use crate::calibrate::X;").is_empty());
    assert!(bad("calibrate/recipe.rs", "gonio_simulator::SimOptions").is_empty());
    assert!(bad("plan/order.rs", "my_crate::engine").is_empty());
    assert!(bad(
        "plan/isotropic.rs",
        "use super::Planner; use super::super::sweep::Sweep;"
    )
    .is_empty());
    assert_eq!(
        bad("plan/isotropic.rs", "use super::fly::X;").len(),
        1,
        "plan/fly is no shared file"
    );
    assert!(bad("compress/pca.rs", "use super::{linalg::X, params::{Params, Method}};").is_empty());
    // the benchmarks' binary room: nothing imports it, its files import no sibling (its
    // `main.rs` dispatches), and `crate::` inside it is the binary's own root
    assert_eq!(bad("cli/plan.rs", "use crate::bench::sim::SimBenchArgs;").len(), 1);
    assert_eq!(bad("view/mod.rs", "use gonio::bench::X;").len(), 1);
    assert_eq!(bad("bench/plan.rs", "use crate::sim::run;").len(), 1);
    assert_eq!(bad("bench/plan.rs", "use super::render::X;").len(), 1);
    assert!(bad("bench/main.rs", "use crate::sim::run; use crate::plan::PlanBenchArgs;").is_empty());
    assert!(bad(
        "bench/sparse.rs",
        "use gonio::cli::bench::RigArgs; use gonio_acquire::plan::Plan; use gonio_simulator::X;"
    )
    .is_empty());
    // declared test files are exempt
    let declared: BTreeSet<String> = ["compress/testdata.rs".to_string()].into();
    assert!(check_file("compress/testdata.rs", "use gonio_simulator::X;", &declared, &modules).is_empty());
    // an item of the folder's mod.rs is not a sibling file
    assert!(bad("synthesize/quilting.rs", "use super::{SynthError, SynthParams};").is_empty());
}

#[test]
fn test_code_is_cut_by_braces_not_by_position() {
    let (code, files) = strip_test_code(
        "use a;\n#[cfg(test)]\nmod tests;\nuse b;\n#[cfg(test)]\nmod inline {\n  fn f() { '}'; \"{\"; /* } */ }\n}\nuse c;\n",
    );
    assert_eq!(files, vec!["tests".to_string()]);
    assert!(
        code.contains("use a;") && code.contains("use b;") && code.contains("use c;"),
        "{code}"
    );
    assert!(!code.contains("fn f"), "{code}");
}
