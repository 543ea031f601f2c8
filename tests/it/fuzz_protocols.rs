//! Fuzzing (proptest) of the remaining outside inputs: serial protocol replies (Zaber ASCII,
//! Newport ESP300), Bonn `.btf` (DFMF) files on read, and calibration recipe TOML.
//!
//! - Zaber: `parse_message` on valid replies mutated byte-wise and on arbitrary lines; and a
//!   `ZaberPort` whose (scripted) device answers every command with fuzzed bytes.
//! - ESP300: an `EspPort` whose device answers queries with fuzzed bytes.
//! - `.btf`: `btf_ubo2014::from_bytes` on a valid small file mutated (flips, truncation,
//!   insertions, huge counts written into the header).
//! - Recipes: `Recipe::parse` on every shipped recipe and the recipe corpus, mutated byte-wise.
//!
//! Seeds live in `tests/campaigns/corpus/{zaber_reply,esp300_reply,recipe}/`; a failing input
//! is kept under `target/tmp/fuzz-failures/<target>/` to be committed there once fixed.
//!
//! Property everywhere: Ok or a typed error within the time limit; never a panic, a hang or
//! an allocation the input's size does not justify.
//!
//! CI budget: `GONIO_FUZZ_CASES` (default 512 per target). Long campaign:
//! `GONIO_FUZZ_CASES=100000 cargo test --release --test fuzz_protocols -- --nocapture`.

use crate::fuzzing;

use fuzzing::{cases, check, corpus};
use gonio::calibrate::recipe::Recipe;
use gonio::compress::btf_ubo2014;
use gonio::compress::dfmf::{ChannelFactors, ColorModel, Dfmf};
use gonio_devices::serial::esp300::EspPort;
use gonio_devices::serial::testing::{ScriptReply, ScriptedTransport};
use gonio_devices::serial::zaber::{self, PortConfig, ZaberPort};
use proptest::prelude::*;
use proptest::test_runner::{Config, TestCaseError, TestRunner};
use std::path::Path;
use std::time::Duration;

const TIME_LIMIT: Duration = Duration::from_secs(20);

/// One case on a helper thread with the time limit (a panic or hang fails the case).
fn guarded<F: FnOnce() + Send + 'static>(f: F) -> Result<(), TestCaseError> {
    fuzzing::guarded(TIME_LIMIT, f).map_err(TestCaseError::fail)
}

fn runner() -> TestRunner {
    TestRunner::new(Config {
        cases: cases(512),
        failure_persistence: None,
        ..Config::default()
    })
}

/// Byte mutations of a seed: (position, xor) flips, a truncation and an insertion.
fn mutated(seed: Vec<u8>) -> impl Strategy<Value = Vec<u8>> {
    (
        prop::collection::vec((any::<usize>(), 1u8..=255), 0..6),
        prop::option::of(any::<usize>()),
        prop::option::of((any::<usize>(), prop::collection::vec(any::<u8>(), 1..16))),
    )
        .prop_map(move |(flips, cut, ins)| {
            let mut b = seed.clone();
            for (at, x) in flips {
                if !b.is_empty() {
                    let i = at % b.len();
                    b[i] ^= x;
                }
            }
            if let Some((at, bytes)) = ins {
                let i = if b.is_empty() { 0 } else { at % b.len() };
                b.splice(i..i, bytes);
            }
            if let Some(c) = cut {
                if !b.is_empty() && c % 4 == 0 {
                    let keep = c % b.len();
                    b.truncate(keep);
                }
            }
            b
        })
}

/// Reply lines (one per file, no line end) of `tests/campaigns/corpus/<sub>/`.
fn reply_corpus(sub: &str) -> Vec<String> {
    corpus(sub)
        .into_iter()
        .map(|b| String::from_utf8_lossy(&b).trim_end_matches(['\r', '\n']).to_string())
        .collect()
}

#[test]
fn fuzz_zaber_reply_lines() {
    let seeds = reply_corpus("zaber_reply");
    let valid = seeds.iter().filter(|s| zaber::parse_message(s).is_ok()).count();
    assert!(valid >= 5, "the Zaber corpus keeps its valid replies ({valid} parse)");
    let mut r = runner();
    let strat = prop_oneof![
        3 => prop::sample::select(seeds).prop_flat_map(|s| mutated(s.into_bytes())),
        1 => prop::collection::vec(any::<u8>(), 0..80),
    ];
    let result = r.run(&strat, |bytes| {
        guarded(move || {
            let line = String::from_utf8_lossy(&bytes).into_owned();
            let _ = zaber::parse_message(&line);
        })
    });
    check("zaber_reply", result, |b| b.clone());
}

/// Run `session` against a device that answers the n-th command with the n-th of 1–3
/// mutated reply lines (cycling), drawn from `seeds`. Every bad reply costs a reply
/// timeout (and retries), hence a quarter of the usual cases.
fn with_garbling_device(target: &str, seeds: Vec<String>, session: fn(ScriptedTransport)) {
    let mut r = TestRunner::new(Config {
        cases: cases(512).div_ceil(4),
        failure_persistence: None,
        ..Config::default()
    });
    let strat = prop::collection::vec(
        prop::sample::select(seeds).prop_flat_map(|s| mutated(format!("{s}\r\n").into_bytes())),
        1..4,
    );
    let result = r.run(&strat, |replies| {
        guarded(move || {
            let mut k = 0;
            session(ScriptedTransport::new(move |_cmd| {
                k += 1;
                vec![ScriptReply::Bytes(replies[k % replies.len()].clone())]
            }))
        })
    });
    // The kept file holds the device's replies in the order it gave them.
    check(target, result, |replies| replies.concat());
}

#[test]
fn fuzz_zaber_port_with_a_garbling_device() {
    with_garbling_device("zaber_port", reply_corpus("zaber_reply"), |t| {
        let port = ZaberPort::with_transport(
            "fuzz",
            Box::new(t),
            PortConfig {
                reply_timeout: Duration::from_millis(20),
                checksums: true,
            },
        );
        for cmd in ["get pos", "move abs 1000", "home", "stop"] {
            let _ = port.command("fuzz-axis", 1, 1, cmd);
        }
    });
}

#[test]
fn fuzz_esp300_port_with_a_garbling_device() {
    with_garbling_device("esp300_port", reply_corpus("esp300_reply"), |t| {
        let port = EspPort::with_transport("fuzz", Box::new(t), Duration::from_millis(20));
        let _ = port.query_number("fuzz-axis", "1TP");
        let _ = port.query("fuzz-axis", "1MD?");
        let _ = port.error("fuzz-axis");
    });
}

/// A valid small DFMF file: 3 lights × 2 views of 4 × 3 texels, 2 components.
fn btf_seed() -> Vec<u8> {
    let (nl, nv, w, h, c) = (3usize, 2usize, 4usize, 3usize, 2usize);
    let ch = |k: f32| ChannelFactors {
        c,
        sigma: vec![2.0, 1.0],
        u: (0..nl * nv * c).map(|i| 0.1 + k + i as f32 * 0.01).collect(),
        sxv: (0..w * h * c).map(|i| 0.2 + k * 0.5 + i as f32 * 0.02).collect(),
    };
    let d = Dfmf {
        color_model: ColorModel::Rgb,
        width: w,
        height: h,
        lights_deg: vec![[0.0, 0.0], [30.0, 90.0], [60.0, 180.0]],
        views_deg: vec![[0.0, 0.0], [45.0, 270.0]],
        channels: vec![ch(0.0), ch(0.1), ch(0.2)],
    };
    btf_ubo2014::to_bytes(&d, btf_ubo2014::Precision::F32, "<fuzz/>").expect("seed encodes")
}

#[test]
fn fuzz_btf_files_on_read() {
    let seed = btf_seed();
    let d = btf_ubo2014::from_bytes(&seed, Path::new("seed.btf")).expect("the seed reads back");
    assert_eq!((d.width, d.height, d.n_lights(), d.n_views()), (4, 3, 3, 2));
    let (mut ok, mut err) = (0u32, 0u32);
    let counts = std::sync::Arc::new(std::sync::Mutex::new((0u32, 0u32)));
    let c2 = counts.clone();
    let mut r = runner();
    let result = r.run(&mutated(seed), move |bytes| {
        let c = c2.clone();
        guarded(move || {
            let res = btf_ubo2014::from_bytes(&bytes, Path::new("fuzz.btf"));
            let mut g = c.lock().unwrap();
            if let Ok(d) = res {
                // What reads must also reconstruct (or refuse) without panicking.
                let _ = d.reconstruct(0, 0);
                g.0 += 1;
            } else {
                g.1 += 1;
            }
        })
    });
    check("btf", result, |b| b.clone());
    let g = *counts.lock().unwrap();
    ok += g.0;
    err += g.1;
    println!(
        "fuzz_btf: {} cases, {ok} read, {err} refused with an error, 0 panics, 0 hangs",
        ok + err
    );
}

/// Seeds: every shipped recipe plus the recipe corpus; each mutated byte-wise.
#[test]
fn fuzz_calibration_recipes() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/calibration/recipes");
    let mut shipped: Vec<std::path::PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    shipped.sort();
    let mut seeds = Vec::new();
    for path in &shipped {
        let text = std::fs::read(path).unwrap();
        Recipe::parse(&String::from_utf8_lossy(&text), &path.display().to_string())
            .unwrap_or_else(|e| panic!("the shipped recipe {} parses: {e}", path.display()));
        seeds.push(text);
    }
    seeds.extend(corpus("recipe"));
    let mut r = runner();
    let strat = prop::sample::select(seeds).prop_flat_map(mutated);
    let result = r.run(&strat, |bytes| {
        guarded(move || {
            let _ = Recipe::parse(&String::from_utf8_lossy(&bytes), "fuzz.toml");
        })
    });
    check("recipe", result, |b| b.clone());
}

/// The harness keeps what it finds: a property that fails leaves its shrunk input in a file
/// named by the panic message, byte for byte.
#[test]
fn a_failing_case_is_kept_as_a_file() {
    let mut r = TestRunner::new(Config {
        cases: 256,
        failure_persistence: None,
        ..Config::default()
    });
    let result = r.run(&prop::collection::vec(any::<u8>(), 0..64), |b| {
        prop_assert!(!b.contains(&0x2a), "contains '*'");
        Ok(())
    });
    let panic = std::panic::catch_unwind(|| check("harness_self_test", result, |b| b.clone()))
        .expect_err("a failing property must fail the target");
    let msg = panic.downcast_ref::<String>().cloned().unwrap_or_default();
    let path = msg
        .split("failing input kept in ")
        .nth(1)
        .and_then(|rest| rest.split(' ').next())
        .unwrap_or_else(|| panic!("no kept file named in {msg:?}"));
    // Shrinking leaves the one offending byte.
    assert_eq!(std::fs::read(path).unwrap(), vec![0x2a]);
}
