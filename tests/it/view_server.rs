//! `gonio view`'s server: token and cookie, path traversal, symlinks out, bad parameters
//! (4xx with a message, never 5xx), limits, and a fuzz test of the API's parameter parsing.
//! Requests are written by hand over TCP so that unnormalized targets reach the server.

use gonio::store::{self, Dataset, ManifestHeader, MeasurementRecord};
use gonio::view::server::{self, ViewError, ViewOptions};
use gonio_devices::image::RgbImage;
use proptest::prelude::*;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::time::Duration;

const TOKEN: &str = "0123456789abcdef0123456789abcdef";

/// A 8×6 dataset on a 4-light × 3-view grid; pair (3, 2) skipped.
fn write_dataset(dir: &Path) {
    let lights = [[0.0, 0.0], [30.0, 0.0], [30.0, 120.0], [30.0, 240.0]];
    let views = [[0.0, 0.0], [40.0, 90.0], [40.0, 270.0]];
    let header = ManifestHeader {
        format: store::FORMAT.into(),
        version: store::FORMAT_VERSION,
        gonio_version: "test".into(),
        created_unix: 1_700_000_000.0,
        rig: serde_json::json!({"name": "test rig"}),
        sample: serde_json::json!({"name": "synthetic"}),
        sweep: serde_json::json!({"name": "t", "lights_deg": lights, "views_deg": views}),
        image_width: 8,
        image_height: 6,
        values: "synthetic".into(),
        seed: 1,
        raw_frames: false,
        calibration: None,
        extra: serde_json::Value::Null,
    };
    let mut ds = Dataset::create(dir, &header, false).unwrap();
    for (v, vd) in views.iter().enumerate() {
        for (l, ld) in lights.iter().enumerate() {
            let index = v * lights.len() + l;
            let mut rec = MeasurementRecord::new(index, index, *ld, *vd);
            rec.wall_time_unix = 1_700_000_000.0 + index as f64;
            if (l, v) == (3, 2) {
                rec.status = store::MeasurementStatus::Skipped { reason: "test".into() };
                ds.store(rec, None, None).unwrap();
                continue;
            }
            let mut img = RgbImage::new(8, 6);
            for (i, x) in img.data.iter_mut().enumerate() {
                *x = 0.05 + 0.01 * ((i + 3 * l + 5 * v) % 40) as f32;
            }
            ds.store(rec, Some(&img), None).unwrap();
        }
    }
    ds.finish(&serde_json::json!({})).unwrap();
}

/// Start a server on `path` (loopback, any port) in a background runtime.
fn start(path: &Path) -> SocketAddr {
    start_with_cache(path, None)
}

fn start_with_cache(path: &Path, cache_dir: Option<&Path>) -> SocketAddr {
    let opts = ViewOptions {
        path: path.to_path_buf(),
        bind: "127.0.0.1".parse().unwrap(),
        port: 0,
        allow_remote: false,
        token: Some(TOKEN.into()),
        cache_dir: cache_dir.map(Path::to_path_buf),
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let bound = rt.block_on(server::bind(&opts)).unwrap();
    let addr = bound.addr;
    assert_eq!(bound.url(), format!("http://{addr}/?token={TOKEN}"));
    std::thread::spawn(move || rt.block_on(bound.serve()));
    addr
}

struct Reply {
    status: u16,
    head: String,
    body: String,
}

fn raw(addr: SocketAddr, request: &str) -> Reply {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    s.write_all(request.as_bytes()).unwrap();
    let mut buf = Vec::new();
    s.read_to_end(&mut buf).unwrap();
    let text = String::from_utf8_lossy(&buf).to_string();
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("no status line in {head:?}"));
    Reply {
        status,
        head: head.to_string(),
        body: body.to_string(),
    }
}

/// GET `target` with the token cookie (or none).
fn get(addr: SocketAddr, target: &str, cookie: bool) -> Reply {
    let c = if cookie {
        format!("Cookie: gonio_token={TOKEN}\r\n")
    } else {
        String::new()
    };
    raw(
        addr,
        &format!("GET {target} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n{c}\r\n"),
    )
}

fn dataset_server() -> (tempfile::TempDir, SocketAddr) {
    let tmp = tempfile::tempdir().unwrap();
    let ds = tmp.path().join("ds");
    write_dataset(&ds);
    std::fs::write(tmp.path().join("secret.txt"), "TOP SECRET").unwrap();
    std::os::unix::fs::symlink(tmp.path().join("secret.txt"), ds.join("link_out.txt")).unwrap();
    std::os::unix::fs::symlink(tmp.path(), ds.join("dir_out")).unwrap();
    let addr = start(&ds);
    (tmp, addr)
}

#[test]
fn token_then_cookie_and_headers_on_every_response() {
    let (_tmp, addr) = dataset_server();
    let r = get(addr, "/", false);
    assert_eq!(r.status, 401, "{}", r.body);
    assert!(r.body.contains("token"), "{}", r.body);
    assert!(r
        .head
        .to_lowercase()
        .contains("content-security-policy: default-src 'none'"));
    assert_eq!(get(addr, "/?token=wrong", false).status, 401);
    assert_eq!(get(addr, "/api/info?token=", false).status, 401);
    let r = get(addr, &format!("/?token={TOKEN}"), false);
    assert_eq!(r.status, 200);
    let lower = r.head.to_lowercase();
    assert!(
        lower.contains(&format!("set-cookie: gonio_token={TOKEN}; httponly; samesite=strict")),
        "{}",
        r.head
    );
    assert!(lower.contains("content-security-policy") && lower.contains("referrer-policy: no-referrer"));
    let r = get(addr, "/api/info", true);
    assert_eq!(r.status, 200, "{}", r.body);
    assert!(
        r.body.contains("\"kind\":\"dataset\"") && r.body.contains("\"gpu\":\"raw\""),
        "{}",
        r.body
    );
    for page in ["/inspect", "/monitor", "/assets/relight.js", "/api/monitor"] {
        assert_eq!(get(addr, page, true).status, 200, "{page}");
    }
    // Read-only and bounded.
    let post = raw(
        addr,
        &format!("POST /api/info HTTP/1.1\r\nHost: {addr}\r\nCookie: gonio_token={TOKEN}\r\nContent-Length: 2\r\nConnection: close\r\n\r\n{{}}"),
    );
    assert_eq!(post.status, 405);
    let long = format!("/api/info?x={}", "a".repeat(5000));
    assert_eq!(get(addr, &long, true).status, 414);
}

#[test]
fn only_files_of_the_dataset_are_reachable() {
    let (_tmp, addr) = dataset_server();
    let ok = get(addr, "/api/file?path=manifest.json", true);
    assert_eq!(ok.status, 200, "{}", ok.body);
    assert!(ok.body.contains("gonio-dataset"));
    assert_eq!(get(addr, "/api/file?path=./images/00000.exr", true).status, 200);
    for target in [
        "/api/file?path=../secret.txt",
        "/api/file?path=images/../../secret.txt",
        "/api/file?path=%2e%2e/secret.txt",
        "/api/file?path=%2E%2E%2Fsecret.txt",
        "/api/file?path=%252e%252e%252fsecret.txt",
        "/api/file?path=%252e%252e/secret.txt",
        "/api/file?path=..%5csecret.txt",
        "/api/file?path=/etc/passwd",
        "/api/file?path=%2fetc%2fpasswd",
        "/api/file?path=link_out.txt",
        "/api/file?path=dir_out/secret.txt",
        "/api/file?path=",
        "/api/file?path=nonexistent",
        "/api/file?path=images",
        "/../secret.txt",
        "/%2e%2e/secret.txt",
        "/assets/..%2f..%2fsecret.txt",
        "/assets/%252e%252e/secret.txt",
        "//etc/passwd",
        "/assets/../../../../etc/passwd",
    ] {
        let r = get(addr, target, true);
        assert!((400..500).contains(&r.status), "{target}: {} {}", r.status, r.body);
        assert!(!r.body.contains("TOP SECRET") && !r.body.contains("root:"), "{target}");
        assert!(!r.body.trim().is_empty(), "{target}: an error needs a message");
    }
    let r = get(addr, "/api/file?path=link_out.txt", true);
    assert!(r.body.contains("symlink") && r.status == 403, "{}", r.body);
    let r = get(addr, "/api/file?path=%252e%252e%252fsecret.txt", true);
    assert!(r.body.contains("double encoding"), "{}", r.body);
}

#[test]
fn malformed_parameters_get_a_4xx_with_a_message() {
    let (_tmp, addr) = dataset_server();
    for (target, needle) in [
        ("/api/render?light=NaN,0", "finite"),
        ("/api/render?light=nan,nan", "light"),
        ("/api/render?view=95,0", "θ must be in [0, 90)"),
        ("/api/render?light=-5,0", "θ must be"),
        ("/api/render?light=inf,0", "finite"),
        ("/api/render?light=30", "θ,φ"),
        ("/api/render?size=100000x100000", "size"),
        ("/api/render?size=600x600", "pixels through the API"),
        ("/api/render?size=0x10", "size"),
        ("/api/render?shape=cube", "plane, sphere or cylinder"),
        ("/api/render?exposure=0", "exposure"),
        ("/api/render?exposure=NaN", "exposure"),
        ("/api/abrdf?x=8&y=0", "must be below 8"),
        ("/api/abrdf?x=0&y=6", "must be below 6"),
        ("/api/abrdf?x=-1&y=0", "whole number"),
        ("/api/abrdf?x=0", "`y` is missing"),
        ("/api/pair?l=4&v=0", "must be below 4"),
        ("/api/pair?l=0&v=0&source=truth", "not available"),
        ("/api/heat?l=0&v=0&a=measured&b=bogus", "not available"),
        ("/api/image?light=30,0", "`view` is missing"),
        ("/api/frame?index=abc", "whole number"),
        ("/api/frame?index=11", "no image"),
        ("/api/raw?view=3", "must be below 3"),
        ("/api/factors?block=0", "no PCA/PVMF factor blocks"),
        ("/api/render?light=%ff%fe,0", ""),
        ("/nope", "no such page"),
    ] {
        let r = get(addr, target, true);
        assert!((400..500).contains(&r.status), "{target}: {} {}", r.status, r.body);
        assert!(r.body.contains(needle), "{target}: {:?} lacks {needle:?}", r.body);
    }
    // Well-formed requests work.
    for target in [
        "/api/render?light=30,20&view=10,200&shape=sphere&size=16x16",
        "/api/image?light=20,50&view=10,0",
        "/api/pair?l=1&v=2&source=measured",
        "/api/abrdf?x=7&y=5",
        "/api/compare?l=0&v=0",
        "/api/frame?index=0",
        "/api/raw?view=2",
        "/api/events",
    ] {
        let r = if target == "/api/events" {
            // A stream: read its first event only.
            let mut s = TcpStream::connect(addr).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
            write!(
                s,
                "GET {target} HTTP/1.1\r\nHost: {addr}\r\nCookie: gonio_token={TOKEN}\r\n\r\n"
            )
            .unwrap();
            let mut buf = vec![0u8; 4096];
            let mut got = String::new();
            while !got.contains("event: snapshot") {
                let n = s.read(&mut buf).unwrap();
                assert!(n > 0, "stream closed: {got}");
                got.push_str(&String::from_utf8_lossy(&buf[..n]));
            }
            assert!(got.contains("\"done\":12") && got.contains("\"skipped\":1"), "{got}");
            continue;
        } else {
            get(addr, target, true)
        };
        assert_eq!(r.status, 200, "{target}: {}", r.body);
    }
}

#[test]
fn a_path_that_is_neither_dataset_nor_known_file_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let txt = tmp.path().join("notes.txt");
    std::fs::write(&txt, "hello, this is not a BTF").unwrap();
    let empty = tmp.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    for (p, why) in [
        (txt, "unknown type"),
        (empty, "without manifest.json"),
        (tmp.path().join("missing"), "cannot be read"),
    ] {
        let opts = ViewOptions {
            path: p.clone(),
            bind: "127.0.0.1".parse().unwrap(),
            port: 0,
            allow_remote: false,
            token: None,
            cache_dir: None,
        };
        let e = rt
            .block_on(server::bind(&opts))
            .err()
            .expect("must be refused")
            .to_string();
        assert!(e.contains(why), "{}: {e}", p.display());
        assert!(
            e.contains("expected a gonio dataset directory") && e.contains(".gbtf") && e.contains(".btf"),
            "{e}"
        );
    }
    // A non-loopback address needs allow_remote.
    let ds = tmp.path().join("ds");
    write_dataset(&ds);
    let opts = ViewOptions {
        path: ds,
        bind: "0.0.0.0".parse().unwrap(),
        port: 0,
        allow_remote: false,
        token: None,
        cache_dir: None,
    };
    let e = rt.block_on(server::bind(&opts)).err().expect("must be refused");
    assert!(matches!(e, ViewError::RemoteRefused { .. }), "{e}");
    assert!(e.to_string().contains("--allow-remote"));
}

fn value() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("NaN".to_string()),
        Just("nan,nan".to_string()),
        Just("inf,-inf".to_string()),
        Just("1e308,1e308".to_string()),
        Just("30,20".to_string()),
        Just("89.999,359.999".to_string()),
        Just("0,0".to_string()),
        Just("16x16".to_string()),
        Just("4294967296x2".to_string()),
        Just("18446744073709551616".to_string()),
        Just("-0".to_string()),
        Just("sphere".to_string()),
        Just("cylinder".to_string()),
        Just("%00".to_string()),
        Just("%2e%2e%2f".to_string()),
        Just("%252e".to_string()),
        Just("measured".to_string()),
        Just("truth".to_string()),
        Just("1.2,0.0,3.1".to_string()),
        Just("0.0,0.0,0.0,0.0,0.0,0.0,0.0,0.0,0.0,0.0,0.0,0.0,0.0,0.0,0.0,0.0,0.0".to_string()),
        (0u32..6, 0u32..5).prop_map(|(l, v)| format!("{l}.{v}")),
        (0u32..20).prop_map(|x| x.to_string()),
        (-1e6f64..1e6).prop_map(|x| x.to_string()),
        (-200f64..200.0, -1e4f64..1e4).prop_map(|(a, b)| format!("{a},{b}")),
        (1u32..40, 1u32..40).prop_map(|(a, b)| format!("{a}x{b}")),
        // Printable junk, percent-encoded as a client would (a raw `<` or `"` is not a valid
        // request target; hyper itself answers those with a bare 400).
        "[ -~]{0,24}".prop_map(|s| s
            .bytes()
            .map(|b| if b.is_ascii_alphanumeric() || b",.-_~%+".contains(&b) {
                (b as char).to_string()
            } else {
                format!("%{b:02X}")
            })
            .collect()),
        proptest::collection::vec(any::<u8>(), 0..12).prop_map(|b| b.iter().map(|x| format!("%{x:02x}")).collect()),
    ]
}

fn name() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("light"),
        Just("view"),
        Just("shape"),
        Just("size"),
        Just("exposure"),
        Just("x"),
        Just("y"),
        Just("l"),
        Just("v"),
        Just("a"),
        Just("b"),
        Just("source"),
        Just("index"),
        Just("block"),
        Just("pairs"),
        Just("path"),
        Just("token"),
        Just("%6c%69ght"),
    ]
    .prop_map(str::to_string)
}

/// The dataset's PVMF compression (2 components), served on its own.
fn gbtf_server(tmp: &Path) -> SocketAddr {
    use gonio::compress::{compress, DatasetViews, Method, Params};
    let views = DatasetViews::open(&tmp.join("ds")).unwrap();
    let (g, _) = compress(&views, &Params::new(Method::Pvmf, 2)).unwrap();
    let file = tmp.join("ds.gbtf");
    g.write(&file).unwrap();
    start(&file)
}

#[test]
fn a_compressed_file_serves_its_factors_and_nothing_else() {
    let (tmp, _) = dataset_server();
    let addr = gbtf_server(tmp.path());
    let info = get(addr, "/api/info", true);
    assert!(
        info.body.contains("\"gpu\":\"pvmf\"") && info.body.contains("\"blocks\":6"),
        "{}",
        info.body
    );
    assert_eq!(get(addr, "/api/factors?block=5", true).status, 200);
    for (target, needle) in [
        ("/api/factors?block=6", "must be below 6"),
        ("/api/file?path=ds.gbtf", "single file"),
        ("/api/raw?view=0", "only for a dataset"),
        ("/api/monitor", "needs a dataset"),
    ] {
        let r = get(addr, target, true);
        assert!(
            (400..500).contains(&r.status) && r.body.contains(needle),
            "{target}: {} {}",
            r.status,
            r.body
        );
    }
}

#[test]
fn fuzzed_parameters_never_get_a_5xx() {
    let (tmp, ds_addr) = dataset_server();
    let addrs = [ds_addr, gbtf_server(tmp.path())];
    let routes = [
        "/api/render",
        "/api/image",
        "/api/pair",
        "/api/compare",
        "/api/heat",
        "/api/abrdf",
        "/api/frame",
        "/api/raw",
        "/api/raw_pairs",
        "/api/needed",
        "/api/factors",
        "/api/file",
        "/api/info",
        "/",
    ];
    let mut runner = proptest::test_runner::TestRunner::new(ProptestConfig {
        cases: 1200,
        failure_persistence: None,
        ..ProptestConfig::default()
    });
    let strategy = (0..routes.len(), proptest::collection::vec((name(), value()), 0..5));
    let statuses = std::cell::RefCell::new(std::collections::BTreeMap::new());
    runner
        .run(&strategy, |(r, params)| {
            let q: Vec<String> = params.iter().map(|(k, v)| format!("{k}={v}")).collect();
            let target = format!("{}?{}", routes[r], q.join("&"));
            let reply = get(addrs[params.len() % 2], &target, true);
            *statuses.borrow_mut().entry(reply.status).or_insert(0usize) += 1;
            prop_assert!(reply.status < 500, "{target}: {} {}", reply.status, reply.body);
            if reply.status >= 400 {
                prop_assert!(!reply.body.trim().is_empty(), "{target}: empty error");
            }
            Ok(())
        })
        .unwrap();
    let statuses = statuses.into_inner();
    eprintln!("fuzz: statuses {statuses:?}");
    assert!(statuses.values().sum::<usize>() >= 1000);
    assert!(statuses.get(&200).copied().unwrap_or(0) > 0, "{statuses:?}");
    assert!(statuses.get(&400).copied().unwrap_or(0) > 0, "{statuses:?}");
}

/// `gonio acquire --view`: the viewer of the dataset being written, in the same process. Its
/// URL is on stderr (after the plan's line); the monitor's JSON advances while the rig works (real-time
/// simulated rig: each capture takes its readout time), and only the token opens it.
#[test]
fn acquire_view_serves_the_monitor_of_the_running_acquisition() {
    use std::io::BufRead;
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("ds");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_gonio"))
        .args([
            "acquire",
            "--sweep",
            "fibonacci:4",
            "--size",
            "16x16",
            "--realtime",
            "--limit",
            "4",
        ])
        .args(["--plan-kicks", "50", "--view", "--out"])
        .arg(&out)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = std::io::BufReader::new(child.stderr.take().unwrap()).lines();
    // The plan's line (size, free space, end time) comes first, then the viewer's URL.
    let mut seen = Vec::new();
    let first = loop {
        let line = lines.next().expect("a stderr line with the viewer's URL").unwrap();
        if line.starts_with("view: ") {
            break line;
        }
        seen.push(line);
        assert!(seen.len() < 20, "no `view: ` line in {seen:?}");
    };
    let url = first.strip_prefix("view: ").unwrap();
    let rest = url.strip_prefix("http://").unwrap();
    let (addr, token) = rest.split_once("/?token=").unwrap();
    let addr: SocketAddr = addr.parse().unwrap();
    assert!(addr.ip().is_loopback(), "{addr}");
    assert_eq!(token.len(), 32, "{token}");
    let monitor = |auth: bool| {
        let q = if auth { format!("?token={token}") } else { String::new() };
        raw(
            addr,
            &format!("GET /api/monitor{q} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"),
        )
    };
    assert_eq!(monitor(false).status, 401);
    let done = |r: &Reply| -> u64 {
        assert_eq!(r.status, 200, "{}", r.body);
        let v: serde_json::Value = serde_json::from_str(&r.body).unwrap();
        v["measured"].as_u64().unwrap()
    };
    let first = done(&monitor(true));
    let mut last = first;
    let t0 = std::time::Instant::now();
    while last < 4 && t0.elapsed() < Duration::from_secs(120) {
        std::thread::sleep(Duration::from_millis(300));
        last = done(&monitor(true));
    }
    assert!(first < 4 && last == 4, "measured went {first} → {last}");
    // After the run it keeps serving until Ctrl-C (SIGINT), then exits with the run's status
    // (3: stopped by --limit).
    let mut saw_end = false;
    for l in lines.by_ref() {
        if l.unwrap().contains("still serving") {
            saw_end = true;
            break;
        }
    }
    assert!(saw_end);
    assert_eq!(done(&monitor(true)), 4);
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let status = child.wait().unwrap();
    assert_eq!(status.code(), Some(3));
}

/// The monitor serves the drift references (`--reference-every`) behind the same token:
/// per reference its run, rig time, ratio per channel and largest drift; none for a dataset
/// without them. The page has their table.
#[test]
fn the_monitor_serves_the_drift_references() {
    let tmp = tempfile::tempdir().unwrap();
    let ds = tmp.path().join("ds");
    write_dataset(&ds);
    let plain = start(&ds);
    let r = get(plain, "/api/monitor", true);
    let v: serde_json::Value = serde_json::from_str(&r.body).unwrap();
    assert_eq!(v["references"], serde_json::json!([]), "{v}");

    let with = tmp.path().join("with");
    let (header, records) = store::load(&ds).unwrap();
    let mut d = Dataset::create(&with, &header, false).unwrap();
    let img = RgbImage::new(8, 6);
    let reference = |mean: [f64; 3], t: f64| store::ReferenceRecord {
        number: 0,
        run: 0,
        rig_time_s: t,
        duration_s: 5.0,
        stored_before: 0,
        after_index: None,
        pair_index: 0,
        light_deg: [0.0, 0.0],
        view_deg: [0.0, 0.0],
        exposure_s: 0.05,
        gain: 1.0,
        mean,
        ratio: [1.0; 3],
        image: String::new(),
        image_sha256: String::new(),
        dark: String::new(),
        dark_sha256: String::new(),
    };
    d.store_reference(reference([0.5, 0.4, 0.2], 1.0), &img, &img).unwrap();
    for rec in records.into_iter().take(3) {
        let image = rec.image.as_ref().map(|_| img.clone());
        d.store(rec, image.as_ref(), None).unwrap();
    }
    d.store_reference(reference([0.51, 0.4, 0.19], 90.0), &img, &img)
        .unwrap();
    drop(d);
    let addr = start(&with);
    assert_eq!(get(addr, "/api/monitor", false).status, 401);
    let r = get(addr, "/api/monitor", true);
    assert_eq!(r.status, 200, "{}", r.body);
    let v: serde_json::Value = serde_json::from_str(&r.body).unwrap();
    let refs = v["references"].as_array().unwrap();
    assert_eq!(refs.len(), 2, "{v}");
    assert_eq!(refs[0]["after_index"], serde_json::Value::Null);
    assert_eq!(
        (refs[1]["number"].as_u64(), refs[1]["run"].as_u64()),
        (Some(1), Some(0))
    );
    assert_eq!(refs[1]["rig_time_s"].as_f64(), Some(90.0));
    assert_eq!(refs[1]["after_index"].as_u64(), Some(2));
    let ratio: Vec<f64> = serde_json::from_value(refs[1]["ratio"].clone()).unwrap();
    assert!(
        (ratio[0] - 1.02).abs() < 1e-9 && ratio[1] == 1.0 && (ratio[2] - 0.95).abs() < 1e-9,
        "{ratio:?}"
    );
    assert!((refs[1]["drift"].as_f64().unwrap() - 0.05).abs() < 1e-9, "{v}");
    assert!(v["references_error"].is_null(), "{v}");
    let page = get(addr, "/monitor", true);
    assert!(page.body.contains("id=\"reftable\""), "{}", page.body);
    let js = get(addr, "/assets/monitor.js", true);
    assert!(js.body.contains("s.references"), "the page draws them");
}

/// A raw dataset too large to decode image by image per click: the first `/api/abrdf`
/// answers 202 with the cache build's progress, later ones 200 with the values of
/// decoding the images directly; the cache lives in `--cache`, not in the dataset, and a
/// `--cache` inside the dataset is refused.
#[test]
fn a_large_raw_dataset_answers_abrdfs_from_its_cache_after_202s_while_it_builds() {
    use gonio::view::source::RawModel;
    use gonio_btf::compress::interp::BtfModel;
    let tmp = tempfile::tempdir().unwrap();
    let ds = tmp.path().join("ds");
    let grid = |n: usize, th: f64| -> Vec<[f64; 2]> { (0..n).map(|k| [th, 360.0 * k as f64 / n as f64]).collect() };
    let f = |l: usize, v: usize, t: usize, c: usize| 0.02 + 0.125 * ((l * 5 + v * 3 + t * 7 + c) % 19) as f32;
    // 128² × 24 pairs × 3 = 1.18 M values, over the direct-decoding bound.
    gonio_btf::compress::testdata::write_test_dataset(&ds, (128, 128), &grid(6, 40.0), &grid(4, 20.0), &[(2, 1)], f);
    let raw = RawModel::open(&ds).unwrap();
    assert!(!raw.abrdf_direct());
    let files_before = std::fs::read_dir(&ds).unwrap().count();
    let cache = tmp.path().join("cache");
    let addr = start_with_cache(&ds, Some(&cache));
    let (x, y) = (100, 37);
    let target = format!("/api/abrdf?x={x}&y={y}");
    let r = get(addr, &target, true);
    assert_eq!(r.status, 202, "{}", r.body);
    let j: serde_json::Value = serde_json::from_str(&r.body).unwrap();
    assert_eq!(j["building"]["images_total"], 23, "{j}");
    assert!(j["message"].as_str().unwrap().contains("building:"), "{j}");
    // Poll (the page polls too); the bound is generous, nothing is timed.
    let mut got = None;
    for _ in 0..3000 {
        let r = get(addr, &target, true);
        match r.status {
            202 => std::thread::sleep(Duration::from_millis(20)),
            200 => {
                got = Some(serde_json::from_str::<serde_json::Value>(&r.body).unwrap());
                break;
            }
            s => panic!("status {s}: {}", r.body),
        }
    }
    let j = got.expect("the cache was built");
    assert_eq!(j["cache"]["pairs"], 23, "{}", j["cache"]);
    assert_eq!(j["cache"]["current"], true);
    let (nl, nv, t) = (6, 4, y * 128 + x);
    let values = j["values"].as_array().unwrap();
    assert_eq!(values.len(), nl * nv);
    for v in 0..nv {
        for l in 0..nl {
            let img = raw.reconstruct(l, v).unwrap();
            let want: Vec<f64> = (0..3).map(|c| img[t * 3 + c] as f64).collect();
            let have: Vec<f64> = (0..3).map(|c| values[v * nl + l][c].as_f64().unwrap()).collect();
            assert_eq!(have, want, "pair ({l}, {v})");
        }
    }
    // The cache is outside the dataset, which did not change.
    assert_eq!(std::fs::read_dir(&ds).unwrap().count(), files_before);
    assert_eq!(std::fs::read_dir(&cache).unwrap().count(), 1);
    // A cache directory inside the dataset is refused, naming why.
    let opts = ViewOptions {
        path: ds.clone(),
        bind: "127.0.0.1".parse().unwrap(),
        port: 0,
        allow_remote: false,
        token: None,
        cache_dir: Some(ds.join("cache")),
    };
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let e = rt
        .block_on(server::bind(&opts))
        .err()
        .expect("must be refused")
        .to_string();
    assert!(e.contains("--cache") && e.contains("inside the served dataset"), "{e}");
}
