//! Fuzzing (proptest) of everything `gonio acquire` parses from outside: rig TOML
//! (`RigSpec::parse`), sample TOML (`SampleSpec::parse`), sweep TOML and CSV
//! (`Sweep::parse_toml` / `Sweep::parse_csv`).
//!
//! Inputs are valid files (the shipped rig and samples, and the committed corpus under
//! `tests/campaigns/corpus/`) mutated byte-wise (flips, truncation, inserted garbage,
//! huge numbers, NaN/inf strings) and structurally (a numeric leaf of the parsed TOML
//! replaced by NaN, ±inf, huge, negative or zero values, keys dropped, tables emptied).
//! Each case runs on a helper thread with a time limit: the property is "returns Ok or Err
//! within the limit, never panics". `fuzz_rig_toml_then_plan` also plans a 4-direction sweep on every rig that parses
//! (it found a hang, fixed by bounding the motion parameters: see
//! `gimbal_rig_with_huge_settle_time_plans_in_bounded_time`).
//!
//! CI budget: `GONIO_FUZZ_CASES` cases per target (default 1024, about 10 s in all).
//! Long campaign: `GONIO_FUZZ_CASES=200000 cargo test --release --test fuzz_inputs -- --nocapture`.

use crate::fuzzing;

use fuzzing::{cases, guarded};
use gonio::plan::{Plan, PlanOptions};
use gonio::sweep::Sweep;
use gonio_devices::rig::RigSpec;
use gonio_devices::Direction;
use gonio_simulator::SampleSpec;
use proptest::prelude::*;
use proptest::test_runner::{Config, TestCaseError, TestRunner};
use std::path::{Path, PathBuf};
use std::time::Duration;

const TIME_LIMIT: Duration = Duration::from_secs(30);

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Seeds: shipped files plus every file of `tests/campaigns/corpus/<sub>/`.
fn seeds(shipped: &[PathBuf], sub: &str) -> Vec<String> {
    let mut out: Vec<String> = shipped.iter().map(|p| std::fs::read_to_string(p).unwrap()).collect();
    let dir = root().join("tests/campaigns/corpus").join(sub);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    for f in files {
        out.push(String::from_utf8_lossy(&std::fs::read(&f).unwrap()).into_owned());
    }
    assert!(!out.is_empty());
    out
}

const GARBAGE: &[&str] = &[
    "nan",
    "NaN",
    "-nan",
    "inf",
    "-inf",
    "1e308",
    "-1e308",
    "1e309",
    "99999999999999999999999999",
    "-9223372036854775809",
    "18446744073709551616",
    "0",
    "-0.0",
    "-1",
    "1e-320",
    "\"",
    "'",
    "[",
    "]]",
    "{",
    "}",
    "=",
    "\n",
    "\n[[axis]]\n",
    "\n[camera]\n",
    ",",
    "\u{0}",
    "\u{feff}",
    "é",
    "#",
    "\"\"\"",
    "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[",
    "1979-05-27T07:32:00Z",
    "true",
];

#[derive(Clone, Debug)]
enum Mutation {
    Flip(usize, u8),
    Truncate(usize),
    Insert(usize, usize),
    Delete(usize, usize),
    /// Replace the n-th number in the text by a garbage token.
    Number(usize, usize),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        (any::<usize>(), any::<u8>()).prop_map(|(p, b)| Mutation::Flip(p, b)),
        any::<usize>().prop_map(Mutation::Truncate),
        (any::<usize>(), 0..GARBAGE.len()).prop_map(|(p, g)| Mutation::Insert(p, g)),
        (any::<usize>(), 1usize..40).prop_map(|(p, n)| Mutation::Delete(p, n)),
        (any::<usize>(), 0..GARBAGE.len()).prop_map(|(p, g)| Mutation::Number(p, g)),
        (any::<usize>(), 0..GARBAGE.len()).prop_map(|(p, g)| Mutation::Number(p, g)),
    ]
}

fn apply(text: &str, muts: &[Mutation]) -> String {
    let mut b = text.as_bytes().to_vec();
    for m in muts {
        let len = b.len().max(1);
        match *m {
            Mutation::Flip(p, x) => {
                if !b.is_empty() {
                    let i = p % b.len();
                    b[i] ^= x | 1;
                }
            }
            Mutation::Truncate(p) => b.truncate(p % len),
            Mutation::Insert(p, g) => {
                let i = p % (b.len() + 1);
                b.splice(i..i, GARBAGE[g].bytes());
            }
            Mutation::Delete(p, n) => {
                let i = p % len;
                let j = (i + n).min(b.len());
                if i < j {
                    b.drain(i..j);
                }
            }
            Mutation::Number(p, g) => {
                let spans: Vec<(usize, usize)> = number_spans(&b);
                if !spans.is_empty() {
                    let (i, j) = spans[p % spans.len()];
                    b.splice(i..j, GARBAGE[g].bytes());
                }
            }
        }
    }
    String::from_utf8_lossy(&b).into_owned()
}

fn number_spans(bytes: &[u8]) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i].is_ascii_digit() {
            let mut j = i;
            while j < bytes.len() && (bytes[j].is_ascii_digit() || bytes[j] == b'.' || bytes[j] == b'e') {
                j += 1;
            }
            out.push((i, j));
            i = j;
        } else {
            i += 1;
        }
    }
    out
}

/// Structural mutation of a TOML document: walk to the n-th leaf and replace it (or drop
/// it, or empty its table).
fn structural(text: &str, pick: usize, action: usize) -> Option<String> {
    let mut v: toml::Value = toml::from_str(text).ok()?;
    let mut leaves = 0usize;
    fn count(v: &toml::Value, n: &mut usize) {
        match v {
            toml::Value::Table(t) => t.values().for_each(|x| count(x, n)),
            toml::Value::Array(a) => a.iter().for_each(|x| count(x, n)),
            _ => *n += 1,
        }
    }
    count(&v, &mut leaves);
    if leaves == 0 {
        return None;
    }
    let target = pick % leaves;
    fn visit(v: &mut toml::Value, n: &mut usize, target: usize, action: usize) -> bool {
        match v {
            toml::Value::Table(t) => {
                let keys: Vec<String> = t.keys().cloned().collect();
                for k in keys {
                    let leaf = !matches!(t[&k], toml::Value::Table(_) | toml::Value::Array(_));
                    if leaf && *n == target && action % 8 == 7 {
                        t.remove(&k);
                        return true;
                    }
                    if visit(t.get_mut(&k).unwrap(), n, target, action) {
                        return true;
                    }
                }
                false
            }
            toml::Value::Array(a) => {
                for x in a.iter_mut() {
                    if visit(x, n, target, action) {
                        return true;
                    }
                }
                false
            }
            leaf => {
                if *n == target {
                    *leaf = match action % 8 {
                        0 => toml::Value::Float(f64::NAN),
                        1 => toml::Value::Float(f64::INFINITY),
                        2 => toml::Value::Float(f64::NEG_INFINITY),
                        3 => toml::Value::Float(1e300),
                        4 => toml::Value::Integer(i64::MAX),
                        5 => toml::Value::Integer(-1),
                        _ => toml::Value::Float(0.0),
                    };
                    return true;
                }
                *n += 1;
                false
            }
        }
    }
    let mut n = 0;
    visit(&mut v, &mut n, target, action);
    toml::to_string(&v).ok()
}

/// A fuzz target: mutate the seeds and feed them to `f`.
fn fuzz<F>(name: &str, seeds: Vec<String>, f: F)
where
    F: Fn(String) + Send + Sync + Clone + 'static,
{
    let mut runner = TestRunner::new(Config {
        cases: cases(1024),
        failure_persistence: None,
        // Shrinking a hang costs TIME_LIMIT per step: report the first failing input.
        max_shrink_iters: 16,
        ..Config::default()
    });
    let n = seeds.len();
    let strategy = (
        0..n,
        prop::collection::vec(mutation(), 0..6),
        any::<usize>(),
        any::<usize>(),
        any::<bool>(),
    );
    let t0 = std::time::Instant::now();
    let input_of = |(s, muts, pick, action, structured): &(usize, Vec<Mutation>, usize, usize, bool)| {
        if *structured {
            structural(&seeds[*s], *pick, *action).unwrap_or_else(|| apply(&seeds[*s], muts))
        } else {
            apply(&seeds[*s], muts)
        }
    };
    let result = runner.run(&strategy, |case| {
        let text = input_of(&case);
        let f = f.clone();
        let input = text.clone();
        guarded(TIME_LIMIT, move || f(input))
            .map_err(|e| TestCaseError::fail(format!("{e}\n--- input ---\n{text}\n---")))
    });
    println!(
        "fuzz {name}: {} cases in {:.1} s",
        cases(1024),
        t0.elapsed().as_secs_f64()
    );
    let target = name.replace([' ', '+'], "_");
    fuzzing::check(&target, result, |case| input_of(case).into_bytes());
}

fn toml_files(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    v.sort();
    v
}

fn plan_small(rig: &RigSpec) {
    let d = vec![
        Direction::from_degrees(0.0, 0.0),
        Direction::from_degrees(30.0, 0.0),
        Direction::from_degrees(45.0, 240.0),
        Direction::from_degrees(75.0, 300.0),
    ];
    let sweep = Sweep {
        name: "fuzz".into(),
        lights: d.clone(),
        views: d,
    };
    let _ = Plan::build(
        rig,
        &sweep,
        &PlanOptions {
            kicks: 0,
            ..Default::default()
        },
    );
}

#[test]
fn fuzz_rig_toml() {
    let seeds = seeds(&toml_files(&root().join("devices/rigs")), "rig");
    fuzz("rig", seeds, |text| {
        let _ = RigSpec::parse(&text, "fuzz.toml");
    });
}

/// Parse, then plan a 4-direction sweep on every rig that parses (its kinematics and motion
/// model must not panic or hang either).
#[test]
fn fuzz_rig_toml_then_plan() {
    let seeds = seeds(&toml_files(&root().join("devices/rigs")), "rig");
    fuzz("rig+plan", seeds, |text| {
        if let Ok(rig) = RigSpec::parse(&text, "fuzz.toml") {
            plan_small(&rig);
        }
    });
}

/// Found by `fuzz_rig_toml_then_plan`: `devices/rigs/gimbal.toml` with one axis's
/// `settle_s = 0.3` replaced by `1e300` parses, and `Plan::build` (also
/// `gonio plan --rig F --plan-time 0`) then never returns; the default two-arm rig with the
/// same change plans at once. Either the rig validation should bound `settle_s` (and the
/// other times/speeds) or the planner must not loop on it.
#[test]
fn gimbal_rig_with_huge_settle_time_plans_in_bounded_time() {
    let text = std::fs::read_to_string(root().join("tests/campaigns/corpus/rig/gimbal_settle_1e300.toml")).unwrap();
    let r = guarded(TIME_LIMIT, move || {
        if let Ok(rig) = RigSpec::parse(&text, "gimbal_settle_1e300.toml") {
            plan_small(&rig);
        }
    });
    assert!(r.is_ok(), "{r:?}");
}

#[test]
fn fuzz_sample_toml() {
    let seeds = seeds(&toml_files(&root().join("simulator/samples")), "sample");
    fuzz("sample", seeds, |text| {
        let _ = SampleSpec::parse(&text, "fuzz.toml", None);
    });
}

#[test]
fn fuzz_sweep_toml() {
    let seeds = seeds(&[], "sweep_toml");
    fuzz("sweep toml", seeds, |text| {
        let _ = Sweep::parse_toml(&text, "fuzz.toml", "fuzz");
    });
}

#[test]
fn fuzz_sweep_csv() {
    let seeds = seeds(&[], "sweep_csv");
    fuzz("sweep csv", seeds, |text| {
        let _ = Sweep::parse_csv(&text, "fuzz.csv", "fuzz");
    });
}

/// Every committed corpus file goes through its parser unmutated too (the corpus holds the
/// interesting inputs found so far, so they stay regression tests).
#[test]
fn corpus_inputs_do_not_panic() {
    let mut n = 0;
    for sub in ["rig", "sample", "sweep_toml", "sweep_csv"] {
        for text in seeds(&[], sub) {
            n += 1;
            let r = match sub {
                "rig" => guarded(TIME_LIMIT, move || {
                    let _ = RigSpec::parse(&text, "corpus.toml");
                }),
                "sample" => guarded(TIME_LIMIT, move || {
                    let _ = SampleSpec::parse(&text, "corpus.toml", None);
                }),
                "sweep_toml" => guarded(TIME_LIMIT, move || {
                    let _ = Sweep::parse_toml(&text, "corpus.toml", "c");
                }),
                _ => guarded(TIME_LIMIT, move || {
                    let _ = Sweep::parse_csv(&text, "corpus.csv", "c");
                }),
            };
            assert!(r.is_ok(), "{sub}: {r:?}");
        }
    }
    println!("fuzz corpus: {n} inputs");
}
