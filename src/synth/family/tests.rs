use super::*;
use std::collections::BTreeMap;

const SPEC: &str = r#"
name = "plastics"
members = 3
seed = 7
sample = "leather"
sweep = "fibonacci:2"
size = 8

[[vary]]
key = "material.0.alpha"
log_uniform = [0.05, 0.5]

[[vary]]
key = "material.0.diffuse_reflectance"
uniform = [[0.1, 0.1, 0.1], [0.8, 0.6, 0.4]]

[[vary]]
key = "seed"
integer = [1, 1000]

[[vary]]
key = "material.0.distribution"
choice = ["ggx", "beckmann"]
"#;

fn family(text: &str) -> Result<Family, FamilyError> {
    Family::parse(text, "spec.toml", Path::new("."))
}

fn err(text: &str) -> String {
    match family(text) {
        Ok(_) => panic!("accepted:\n{text}"),
        Err(e) => e.to_string(),
    }
}

/// Every file under `dir` by relative path; the manifest and journal without their
/// wall-clock readings (creation and storage times, and the CRC over the latter).
fn files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    fn walk(root: &Path, dir: &Path, out: &mut BTreeMap<String, Vec<u8>>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
                continue;
            }
            let rel = p.strip_prefix(root).unwrap().display().to_string();
            let mut bytes = std::fs::read(&p).unwrap();
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            if name == "manifest.json" {
                let mut v: serde_json::Value = serde_json::from_slice(&bytes).unwrap();
                v["created_unix"] = serde_json::Value::Null;
                for r in v["records"].as_array_mut().unwrap() {
                    r["wall_time_unix"] = serde_json::Value::Null;
                }
                bytes = serde_json::to_vec(&v).unwrap();
            } else if name == "journal.jsonl" {
                let mut lines = vec![];
                for l in bytes.split(|&b| b == b'\n').filter(|l| !l.is_empty()) {
                    let mut v: serde_json::Value = serde_json::from_slice(l).unwrap();
                    v["crc"] = serde_json::Value::Null;
                    v["rec"]["wall_time_unix"] = serde_json::Value::Null;
                    lines.push(v.to_string());
                }
                bytes = lines.join("\n").into_bytes();
            }
            out.insert(rel, bytes);
        }
    }
    let mut out = BTreeMap::new();
    walk(dir, dir, &mut out);
    out
}

#[test]
fn draws_are_in_range_reproducible_and_become_the_labels() {
    let f = family(SPEC).unwrap();
    let g = family(SPEC).unwrap();
    let mut alphas = vec![];
    for m in 0..3 {
        let (a, b) = (f.member(m).unwrap(), g.member(m).unwrap());
        assert_eq!(a.labels, b.labels, "member {m} drawn twice differently");
        let alpha = a.labels["material.0.alpha"].as_f64().unwrap();
        assert!((0.05..=0.5).contains(&alpha), "alpha {alpha}");
        let rho = a.labels["material.0.diffuse_reflectance"].as_array().unwrap();
        let hi = [0.8, 0.6, 0.4];
        for (i, r) in rho.iter().enumerate() {
            let r = r.as_f64().unwrap();
            assert!((0.1..=hi[i]).contains(&r), "component {i}: {r}");
        }
        let seed = a.labels["seed"].as_i64().unwrap();
        assert!((1..=1000).contains(&seed));
        // The label is what the member's sample holds.
        let sample = serde_json::to_value(&a.spec).unwrap();
        assert_eq!(sample["material"][0]["alpha"].as_f64(), Some(alpha));
        assert_eq!(a.sample, format!("plastics-s7-{m:04}"));
        alphas.push(alpha);
    }
    assert!(alphas[0] != alphas[1] && alphas[1] != alphas[2], "{alphas:?}");
    // Another seed, other draws.
    let other = family(&SPEC.replace("seed = 7", "seed = 8")).unwrap();
    assert_ne!(other.member(0).unwrap().labels, f.member(0).unwrap().labels);
    assert_ne!(
        other.member(0).unwrap().sample,
        f.member(0).unwrap().sample,
        "a fresh draw is another sample"
    );
}

#[test]
fn bad_specs_are_refused_naming_the_key_and_the_fix() {
    let e = err(&SPEC.replace("material.0.alpha", "material.5.alpha"));
    assert!(e.contains("material.5.alpha") && e.contains("2 entries"), "{e}");
    let e = err(&SPEC.replace("material.0.alpha", "material.0.alhpa"));
    // A new key in a table is allowed (optional parameters); the sample refuses unknown ones.
    assert!(e.contains("alhpa") && e.contains("member 0"), "{e}");
    let e = err(&SPEC.replace("key = \"seed\"", "key = \"height\""));
    assert!(e.contains("`height`") && e.contains("table"), "{e}");
    let e = err(&SPEC.replace("log_uniform = [0.05, 0.5]", "log_uniform = [0.0, 0.5]"));
    assert!(e.contains("> 0"), "{e}");
    let e = err(&SPEC.replace("log_uniform = [0.05, 0.5]", "uniform = [0.5, 0.05]"));
    assert!(e.contains("lo ≤ hi"), "{e}");
    let e = err(&SPEC.replace("log_uniform = [0.05, 0.5]", "uniform = [0.1, 0.2]\ninteger = [1, 2]"));
    assert!(e.contains("exactly one"), "{e}");
    let e = err(&SPEC.replace("log_uniform = [0.05, 0.5]", "uniform = [-2.0, -1.0]"));
    assert!(e.contains("member 0") && e.contains("narrow the ranges"), "{e}");
    let e = err(&SPEC.replace("members = 3", "members = 0"));
    assert!(e.contains("members = 0"), "{e}");
    let e = err(&SPEC.replace("sample = \"leather\"", "sample = \"no-such-sample\""));
    assert!(e.contains("no-such-sample"), "{e}");
    let e = err(&SPEC.replace("size = 8", "size = 3"));
    assert!(e.contains("size = 3"), "{e}");
    let e = err(&SPEC.replace(
        "uniform = [[0.1, 0.1, 0.1], [0.8, 0.6, 0.4]]",
        "uniform = [[0.1, 0.1], [0.8, 0.6]]",
    ));
    assert!(e.contains("list of 3"), "{e}");
}

#[test]
fn shards_write_the_single_process_family_and_reruns_keep_complete_members() {
    let f = family(SPEC).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let (one, split) = (tmp.path().join("one"), tmp.path().join("split"));
    let r = f.generate(&one, None, false, &|_| {}).unwrap();
    assert_eq!(r.rendered, vec![0, 1, 2]);
    assert_eq!(r.images, 3 * 4);
    for i in 1..=2 {
        let s = Shard { index: i, count: 2 };
        f.generate(&split, Some(s), false, &|_| {}).unwrap();
    }
    let (a, b) = (files(&one), files(&split));
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    for (k, v) in &a {
        assert!(
            v == &b[k],
            "{k} differs between one process and two shards:\n{}\n{}",
            String::from_utf8_lossy(v),
            String::from_utf8_lossy(&b[k])
        );
    }
    let csv = String::from_utf8(a["labels.csv"].clone()).unwrap();
    assert!(
        csv.starts_with("member,dir,sample,material.0.alpha,material.0.diffuse_reflectance[0]"),
        "{csv}"
    );
    assert_eq!(csv.lines().count(), 4);

    // A rerun keeps what is complete; a member without its manifest is rendered again.
    std::fs::remove_file(one.join("members/0001/manifest.json")).unwrap();
    let r = f.generate(&one, None, false, &|_| {}).unwrap();
    assert_eq!((r.kept.clone(), r.rendered.clone()), (vec![0, 2], vec![1]));
    assert_eq!(files(&one), a);

    // Another spec into the same directory is refused; with --force its members are redone.
    let other = family(&SPEC.replace("seed = 7", "seed = 9")).unwrap();
    let e = other.generate(&one, None, false, &|_| {}).unwrap_err().to_string();
    assert!(e.contains("another family") && e.contains("--force"), "{e}");
    let r = other.generate(&one, None, true, &|_| {}).unwrap();
    assert_eq!(r.rendered, vec![0, 1, 2]);

    let e = f
        .generate(&split, Some(Shard { index: 1, count: 4 }), false, &|_| {})
        .unwrap_err();
    assert!(e.to_string().contains("3 members cannot be split into 4"), "{e}");
}

#[test]
fn more_members_keep_the_first_draws_and_say_so_in_the_stored_spec() {
    let f = family(SPEC).unwrap();
    let g = family(SPEC).unwrap().with_members(5).unwrap();
    assert_eq!(g.spec.members, 5);
    for m in 0..3 {
        assert_eq!(f.member(m).unwrap().labels, g.member(m).unwrap().labels, "member {m}");
    }
    assert!(g.member(4).is_ok());
    // The stored spec is the original text with only the members line rewritten.
    assert_eq!(g.text, SPEC.replace("members = 3", "members = 5"));
    assert!(family(&g.text).is_ok());
    assert!(family(SPEC).unwrap().with_members(0).is_err());
    let no_line = SPEC.replace("members = 3\n", "members=3\n");
    assert!(family(&no_line).unwrap().with_members(4).is_ok());
}
