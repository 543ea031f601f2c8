//! Tests of the emulators: protocol engines driven directly with a synthetic clock, and the
//! pty loop (faults that act on bytes, disconnect/reconnect, state file) through a real pty.

use super::*;
use std::io::{BufRead, BufReader, Write};
use std::time::{Duration, Instant};

fn zaber(axes: usize, faults: &[&str]) -> Box<dyn Controller> {
    let cfg = EmulatorConfig::new(Protocol::Zaber, axes).with_faults(FaultPlan::parse(faults).unwrap());
    controller(&cfg, None).unwrap()
}

fn esp(axes: usize, faults: &[&str]) -> Box<dyn Controller> {
    let cfg = EmulatorConfig::new(Protocol::Esp300, axes).with_faults(FaultPlan::parse(faults).unwrap());
    controller(&cfg, None).unwrap()
}

fn one(c: &mut dyn Controller, line: &str, now: Instant) -> String {
    let h = c.handle(line, now);
    assert!(!h.disconnect, "{line}");
    assert_eq!(h.replies.len(), 1, "{line}: {:?}", h.replies);
    h.replies[0].clone()
}

fn secs(t0: Instant, s: f64) -> Instant {
    t0 + Duration::from_secs_f64(s)
}

#[test]
fn zaber_home_move_busy_then_idle_at_the_motion_model_time() {
    let mut z = zaber(1, &[]);
    let t0 = Instant::now();
    assert_eq!(one(z.as_mut(), "/", t0), "@01 0 OK IDLE WR 0");
    assert_eq!(one(z.as_mut(), "/1 1 home", t0), "@01 1 OK IDLE -- 0");
    // home from 0 is no move at all
    assert_eq!(one(z.as_mut(), "/1 1 get pos", t0), "@01 1 OK IDLE -- 0");
    assert_eq!(one(z.as_mut(), "/1 1 5 move abs 90000", t0), "@01 1 5 OK BUSY -- 0");
    // 90° at 90 °/s, 720 °/s²: 1 s cruise + 0.125 s = 1.125 s
    let t_end = MotionModel {
        max_velocity: 90.0,
        acceleration: 720.0,
        jerk: None,
        settle_time: 0.0,
        deadband: 0.0,
    }
    .profile_time(90.0);
    assert!((t_end - 1.125).abs() < 1e-9);
    let mid = one(z.as_mut(), "/1 1 get pos", secs(t0, 0.5));
    assert!(mid.starts_with("@01 1 OK BUSY -- "), "{mid}");
    let p: i64 = mid.rsplit(' ').next().unwrap().parse().unwrap();
    assert!(p > 30_000 && p < 60_000, "{p}");
    assert_eq!(one(z.as_mut(), "/1 1", secs(t0, 1.2)), "@01 1 OK IDLE -- 0");
    assert_eq!(one(z.as_mut(), "/1 1 get pos", secs(t0, 1.2)), "@01 1 OK IDLE -- 90000");
    assert_eq!(
        one(z.as_mut(), "/1 1 move rel -1000", secs(t0, 1.2)),
        "@01 1 OK BUSY -- 0"
    );
    assert_eq!(one(z.as_mut(), "/1 1 get pos", secs(t0, 3.0)), "@01 1 OK IDLE -- 89000");
}

#[test]
fn zaber_rejects_with_reasons_and_never_panics() {
    let mut z = zaber(2, &[]);
    let t = Instant::now();
    assert_eq!(
        one(z.as_mut(), "/1 1 move abs 999999999", t),
        "@01 1 RJ IDLE WR BADDATA"
    );
    assert_eq!(one(z.as_mut(), "/1 1 move abs banana", t), "@01 1 RJ IDLE WR BADDATA");
    assert_eq!(one(z.as_mut(), "/1 1 move abs", t), "@01 1 RJ IDLE WR BADDATA");
    assert_eq!(one(z.as_mut(), "/1 1 move sideways", t), "@01 1 RJ IDLE WR BADCOMMAND");
    assert_eq!(one(z.as_mut(), "/1 3 get pos", t), "@01 0 RJ IDLE WR BADAXIS");
    assert_eq!(one(z.as_mut(), "/1 1 frobnicate", t), "@01 1 RJ IDLE WR BADCOMMAND");
    assert_eq!(
        one(z.as_mut(), "/1 1 get no.such.setting", t),
        "@01 1 RJ IDLE WR BADCOMMAND"
    );
    assert_eq!(one(z.as_mut(), "/1 1 get pos:00", t), "@01 1 RJ IDLE WR BADDATA");
    assert_eq!(one(z.as_mut(), "/1 0 get pos", t), "@01 0 OK IDLE WR 0 0");
    // Not for us / not a command: silence.
    assert!(z.handle("/7 1 get pos", t).replies.is_empty());
    assert!(z.handle("hello", t).replies.is_empty());
    for junk in [
        "/",
        "/ / /",
        "/99999999999 1 home",
        "/1 1 1 1 1 1",
        "/:",
        "/1 1 move abs 1e308",
        "/\u{0}\u{ff}",
        "/1 1 move rel NaN",
    ] {
        let _ = z.handle(junk, t);
    }
    assert_eq!(one(z.as_mut(), "/1 1 get pos", t), "@01 1 OK IDLE WR 0");
}

#[test]
fn zaber_checksummed_replies_and_warnings() {
    let mut z = zaber(1, &[]);
    let t = Instant::now();
    let body = "1 1 set comm.checksum 1";
    let line = format!("/{body}:{:02X}", zaber::checksum(body.as_bytes()));
    let r = one(z.as_mut(), &line, t);
    let (b, c) = r[1..].rsplit_once(':').unwrap();
    assert_eq!(b, "01 1 OK IDLE WR 0");
    assert_eq!(u8::from_str_radix(c, 16).unwrap(), zaber::checksum(b.as_bytes()));
    one(z.as_mut(), "/1 1 set comm.checksum 0", t);
    assert_eq!(one(z.as_mut(), "/1 1 warnings", t), "@01 1 OK IDLE WR 01 WR");
    one(z.as_mut(), "/1 1 home", t);
    one(z.as_mut(), "/1 1 move abs 50000", t);
    // interrupted by stop, which decelerates: at 0.1 s the axis runs at 72 °/s and needs
    // another 0.1 s at 720 °/s² to come to rest, BUSY until then
    assert_eq!(one(z.as_mut(), "/1 1 stop", secs(t, 0.1)), "@01 1 OK BUSY NI 0");
    assert_eq!(
        one(z.as_mut(), "/1 1 warnings clear", secs(t, 0.3)),
        "@01 1 OK IDLE -- 01 NI"
    );
    assert_eq!(one(z.as_mut(), "/1 1", secs(t, 0.3)), "@01 1 OK IDLE -- 0");
}

fn pos_of(reply: &str) -> i64 {
    reply.rsplit(' ').next().unwrap().parse().unwrap()
}

#[test]
fn zaber_per_move_speed_velocity_moves_and_decelerating_stop() {
    let mut z = zaber(1, &[]);
    let t = Instant::now();
    one(z.as_mut(), "/1 1 home", t);
    for bad in [
        "/1 1 move abs 100 0 5",
        "/1 1 move abs 100 5",
        "/1 1 move vel x",
        "/1 1 move vel 5 0",
    ] {
        assert_eq!(one(z.as_mut(), bad, t), "@01 1 RJ IDLE -- BADDATA", "{bad}");
    }
    // SPEED 16384 = 10 000 µsteps/s = 10 °/s, ACCEL 16 = 97 656.25 µsteps/s² = 97.66 °/s²:
    // at 1 s the axis is at ½·a·t_acc² + v·(1 − t_acc) = 9.488°, done after 2.1024 s
    assert_eq!(one(z.as_mut(), "/1 1 move abs 20000 16384 16", t), "@01 1 OK BUSY -- 0");
    let r = one(z.as_mut(), "/1 1 get pos", secs(t, 1.0));
    assert!(r.starts_with("@01 1 OK BUSY"), "{r}");
    assert!((pos_of(&r) - 9488).abs() <= 1, "{r}");
    assert!(one(z.as_mut(), "/1 1", secs(t, 2.09)).contains("BUSY"));
    assert_eq!(one(z.as_mut(), "/1 1 get pos", secs(t, 2.11)), "@01 1 OK IDLE -- 20000");
    // `maxspeed`/`accel` are untouched by a per-move profile
    assert_eq!(
        one(z.as_mut(), "/1 1 get maxspeed", secs(t, 2.11)),
        "@01 1 OK IDLE -- 147456"
    );
    // move vel at 10 °/s (axis accel 720 °/s²: up to speed in 1/72 s), stop after 1 s:
    // 10 °/s decelerates in 1/72 s over 1/144°; BUSY meanwhile
    let t = secs(t, 3.0);
    assert_eq!(one(z.as_mut(), "/1 1 move vel 16384", t), "@01 1 OK BUSY -- 0");
    let at_stop = 20_000.0 + 1000.0 * (10.0 / 144.0 + 10.0 * (1.0 - 1.0 / 72.0));
    assert_eq!(one(z.as_mut(), "/1 1 stop", secs(t, 1.0)), "@01 1 OK BUSY NI 0");
    assert!(one(z.as_mut(), "/1 1", secs(t, 1.01)).contains("BUSY"));
    let r = one(z.as_mut(), "/1 1 get pos", secs(t, 1.02));
    assert!(r.starts_with("@01 1 OK IDLE NI"), "{r}");
    let rest = at_stop + 1000.0 * 10.0 / 144.0;
    assert!((pos_of(&r) as f64 - rest).abs() <= 1.0, "{r} vs {rest}");
    // a velocity move ends at the travel limit (180°), negative velocities run backwards
    one(z.as_mut(), "/1 1 warnings clear", secs(t, 2.0));
    assert_eq!(
        one(z.as_mut(), "/1 1 move vel -163840 1638", secs(t, 2.0)),
        "@01 1 OK BUSY -- 0"
    );
    assert_eq!(
        one(z.as_mut(), "/1 1 get pos", secs(t, 60.0)),
        "@01 1 OK IDLE -- -180000"
    );
    // estop is immediate
    one(z.as_mut(), "/1 1 move abs 0", secs(t, 61.0));
    assert_eq!(one(z.as_mut(), "/1 1 estop", secs(t, 61.1)), "@01 1 OK IDLE NI 0");
}

#[test]
fn zaber_daisy_chain_answers_in_order() {
    let mut cfg = EmulatorConfig::new(Protocol::Zaber, 1);
    cfg.devices = 2;
    let mut z = controller(&cfg, None).unwrap();
    let r = z.handle("/get device.id", Instant::now()).replies;
    assert_eq!(r, vec!["@01 0 OK IDLE WR 99001", "@02 0 OK IDLE WR 99001"]);
    let r = z.handle("/2 0 get system.serial", Instant::now()).replies;
    assert_eq!(r, vec!["@02 0 OK IDLE WR 90000002"]);
}

#[test]
fn zaber_stall_keeps_busy_without_progress_until_stop() {
    let mut z = zaber(1, &["stall:at-move=2"]);
    let t = Instant::now();
    one(z.as_mut(), "/1 1 home", t);
    one(z.as_mut(), "/1 1 move abs 10000", t);
    one(z.as_mut(), "/1 1 move abs 90000", secs(t, 1.0));
    let a = one(z.as_mut(), "/1 1 get pos", secs(t, 3.0));
    let b = one(z.as_mut(), "/1 1 get pos", secs(t, 30.0));
    assert!(a.starts_with("@01 1 OK BUSY"), "{a}");
    assert_eq!(a, b, "a stalled axis makes no progress");
    let p: i64 = a.rsplit(' ').next().unwrap().parse().unwrap();
    assert_eq!(p, 50_000, "stalls half way");
    assert_eq!(one(z.as_mut(), "/1 1 stop", secs(t, 31.0)), "@01 1 OK IDLE NI 0");
}

#[test]
fn zaber_stall_stop_reports_fs_and_esp_a_following_error() {
    let mut z = zaber(1, &["stall-stop:at-move=1"]);
    let t = Instant::now();
    one(z.as_mut(), "/1 1 home", t);
    one(z.as_mut(), "/1 1 move abs -20000", t);
    assert_eq!(one(z.as_mut(), "/1 1 get pos", secs(t, 5.0)), "@01 1 OK IDLE FS -10000");
    assert_eq!(
        one(z.as_mut(), "/1 1 warnings clear", secs(t, 5.0)),
        "@01 1 OK IDLE -- 01 FS"
    );
    let mut e = esp(2, &["stall-stop:at-move=1"]);
    e.handle("2MO;2PA8", t);
    assert_eq!(one(e.as_mut(), "2MD?", secs(t, 5.0)), "1");
    assert_eq!(one(e.as_mut(), "2TP", secs(t, 5.0)), "4.00000");
    assert_eq!(
        one(e.as_mut(), "TB?", secs(t, 5.0))
            .split(", ")
            .map(String::from)
            .collect::<Vec<_>>()[2],
        "FOLLOWING ERROR THRESHOLD EXCEEDED"
    );
}

#[test]
fn zaber_limit_switch_stops_half_way_with_wl() {
    let mut z = zaber(1, &["limit:at-move=1"]);
    let t = Instant::now();
    one(z.as_mut(), "/1 1 home", t);
    one(z.as_mut(), "/1 1 move abs 20000", t);
    assert_eq!(one(z.as_mut(), "/1 1", secs(t, 5.0)), "@01 1 OK IDLE WL 0");
    assert_eq!(one(z.as_mut(), "/1 1 get pos", secs(t, 5.0)), "@01 1 OK IDLE WL 10000");
    // the next move clears it
    assert_eq!(one(z.as_mut(), "/1 1 move abs 0", secs(t, 5.0)), "@01 1 OK BUSY -- 0");
}

#[test]
fn zaber_disconnect_fault_executes_nothing() {
    let mut z = zaber(1, &["disconnect:at-move=2"]);
    let t = Instant::now();
    one(z.as_mut(), "/1 1 move abs 1000", t);
    let h = z.handle("/1 1 move abs 5000", secs(t, 1.0));
    assert!(h.disconnect && h.replies.is_empty());
    assert_eq!(z.state(secs(t, 2.0)).axes[0].pos, 1000.0);
    // move 3 is fine again
    one(z.as_mut(), "/1 1 move abs 2000", secs(t, 2.0));
}

#[test]
fn esp_enable_home_move_and_errors() {
    let mut e = esp(2, &[]);
    let t = Instant::now();
    assert!(e.handle("1PA10", t).replies.is_empty());
    assert_eq!(one(e.as_mut(), "TE?", t), "113", "motor not enabled");
    assert_eq!(one(e.as_mut(), "TE?", t), "0");
    assert!(e.handle("1MO;1OR1", t).replies.is_empty());
    assert_eq!(one(e.as_mut(), "1MO?", t), "1");
    assert!(e.handle("1PA45.5", t).replies.is_empty());
    assert_eq!(one(e.as_mut(), "1MD?", secs(t, 0.1)), "0");
    assert_eq!(one(e.as_mut(), "1MD?", secs(t, 2.0)), "1");
    assert_eq!(one(e.as_mut(), "1TP", secs(t, 2.0)), "45.50000");
    e.handle("1PR-5.5", secs(t, 2.0));
    assert_eq!(one(e.as_mut(), "1TP", secs(t, 4.0)), "40.00000");
    assert_eq!(one(e.as_mut(), "TP", secs(t, 4.0)), "40.00000,0.00000");
    e.handle("1PA500", secs(t, 4.0));
    assert_eq!(
        one(e.as_mut(), "TB?", secs(t, 4.0)).split(", ").nth(2),
        Some("POSITIVE SOFTWARE LIMIT DETECTED")
    );
    e.handle("1PA-500", secs(t, 4.0));
    assert_eq!(one(e.as_mut(), "TE?", secs(t, 4.0)), "107");
    assert!(one(e.as_mut(), "VE?", t).starts_with("ESP300 Version"));
}

#[test]
fn esp_bad_input_queues_errors_and_never_panics() {
    let mut e = esp(1, &[]);
    let t = Instant::now();
    for (line, code) in [
        ("XX", 6),
        ("1ZZ", 6),
        ("PA5", 37),
        ("4MO", 9),
        ("0MO", 9),
        ("1PA", 38),
        ("1PAbanana", 7),
        ("1", 6),
        ("\u{1}\u{ff}", 6),
        ("99999999999999999999PA1", 9),
    ] {
        assert!(e.handle(line, t).replies.is_empty(), "{line}");
        assert_eq!(one(e.as_mut(), "TE?", t), code.to_string(), "{line}");
    }
    // the queue holds 10 errors, oldest lost
    for _ in 0..15 {
        e.handle("XX", t);
    }
    let mut n = 0;
    while one(e.as_mut(), "TE?", t) != "0" {
        n += 1;
    }
    assert_eq!(n, 10);
    let _ = e.handle(";;;1MO;;", t);
    assert_eq!(one(e.as_mut(), "1MO?", t), "1");
}

#[test]
fn esp_limit_switch_and_stall_faults() {
    let mut e = esp(1, &["limit:at-move=1", "stall:at-move=2"]);
    let t = Instant::now();
    e.handle("1MO", t);
    e.handle("1PA-20", t);
    assert_eq!(one(e.as_mut(), "1MD?", secs(t, 5.0)), "1");
    assert_eq!(one(e.as_mut(), "1TP", secs(t, 5.0)), "-10.00000");
    assert_eq!(one(e.as_mut(), "TE?", secs(t, 5.0)), "105", "negative hardware limit");
    e.handle("1PA30", secs(t, 5.0));
    assert_eq!(one(e.as_mut(), "1MD?", secs(t, 60.0)), "0", "stalled: never done");
    assert_eq!(one(e.as_mut(), "1TP", secs(t, 60.0)), "10.00000");
    e.handle("1ST", secs(t, 61.0));
    assert_eq!(one(e.as_mut(), "1MD?", secs(t, 61.0)), "1");
}

#[test]
fn esp_velocity_and_acceleration_apply_to_the_next_move_and_st_decelerates() {
    let mut e = esp(1, &[]);
    let t = Instant::now();
    e.handle("1MO", t);
    e.handle("1OR", t);
    // 10 °/s at 100 °/s²: 20° take 2 + 0.1 s; at 1 s the axis is at 0.5 + 9 = 9.5°
    e.handle("1VA10;1AC100", t);
    assert_eq!(one(e.as_mut(), "1VA?", t), "10.00000");
    e.handle("1PA20", t);
    // a new VA while moving is for the next move; the flight keeps its velocity
    e.handle("1VA90", secs(t, 0.5));
    let p: f64 = one(e.as_mut(), "1TP", secs(t, 1.0)).parse().unwrap();
    assert!((p - 9.5).abs() < 1e-3, "{p}");
    assert_eq!(one(e.as_mut(), "1MD?", secs(t, 2.09)), "0");
    assert_eq!(one(e.as_mut(), "1MD?", secs(t, 2.11)), "1");
    // ST decelerates at AC (100 °/s²): from 90 °/s that is 0.9 s, not done meanwhile
    let t = secs(t, 3.0);
    e.handle("1PA-170", t);
    e.handle("1ST", secs(t, 1.5));
    assert_eq!(one(e.as_mut(), "1MD?", secs(t, 1.6)), "0");
    assert_eq!(one(e.as_mut(), "1MD?", secs(t, 2.5)), "1");
    // AB stops at once
    e.handle("1PA0", secs(t, 3.0));
    e.handle("1AB", secs(t, 3.5));
    assert_eq!(one(e.as_mut(), "1MD?", secs(t, 3.5)), "1");
    assert_eq!(one(e.as_mut(), "TE?", secs(t, 3.5)), "0");
}

// ---- through a real pty ----

struct Client {
    reader: BufReader<std::fs::File>,
    writer: std::fs::File,
}

impl Client {
    fn open(path: &Path) -> Client {
        let f = std::fs::OpenOptions::new().read(true).write(true).open(path).unwrap();
        // Reads must not hang a failing test forever.
        set_read_timeout(&f, 10);
        Client {
            writer: f.try_clone().unwrap(),
            reader: BufReader::new(f),
        }
    }

    fn send(&mut self, line: &str) {
        self.writer.write_all(format!("{line}\r\n").as_bytes()).unwrap();
    }

    /// One reply line without CRLF; None on timeout.
    fn line(&mut self) -> Option<Vec<u8>> {
        let mut buf = Vec::new();
        match self.reader.read_until(b'\n', &mut buf) {
            Ok(0) | Err(_) => None,
            Ok(_) => {
                while buf.last().is_some_and(|b| *b == b'\n' || *b == b'\r') {
                    buf.pop();
                }
                Some(buf)
            }
        }
    }

    fn ask(&mut self, line: &str) -> Option<String> {
        self.send(line);
        self.line().map(|b| String::from_utf8_lossy(&b).into_owned())
    }
}

/// VTIME-based read timeout (tenths of a second) on the client side of the pty.
fn set_read_timeout(f: &std::fs::File, tenths: u8) {
    use std::os::fd::AsRawFd;
    // SAFETY: termios calls on an open tty descriptor.
    unsafe {
        let mut t: libc::termios = std::mem::zeroed();
        assert_eq!(libc::tcgetattr(f.as_raw_fd(), &mut t), 0);
        libc::cfmakeraw(&mut t);
        t.c_cc[libc::VMIN] = 0;
        t.c_cc[libc::VTIME] = tenths;
        assert_eq!(libc::tcsetattr(f.as_raw_fd(), libc::TCSANOW, &t), 0);
    }
}

fn spawn(protocol: Protocol, faults: &[&str]) -> EmulatorHandle {
    let cfg = EmulatorConfig::new(protocol, 1).with_faults(FaultPlan::parse(faults).unwrap());
    spawn_pty(cfg).unwrap()
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("gonio-emulate-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn pty_garbled_and_dropped_replies() {
    let h = spawn(Protocol::Zaber, &["garble:every=3", "drop:at=5"]);
    let mut c = Client::open(h.path());
    assert_eq!(c.ask("/1 1 get pos").as_deref(), Some("@01 1 OK IDLE WR 0"));
    assert_eq!(c.ask("/1 1 home").as_deref(), Some("@01 1 OK IDLE -- 0"));
    c.send("/1 1 get pos");
    let g = c.line().unwrap();
    assert_eq!(g, faults::garble(b"@01 1 OK IDLE -- 0"), "reply 3 garbled");
    assert_eq!(c.ask("/1 1").as_deref(), Some("@01 1 OK IDLE -- 0"));
    assert_eq!(c.ask("/1 1"), None, "reply to command 5 dropped");
    c.send("/1 1");
    assert_ne!(c.line().unwrap(), b"@01 1 OK IDLE -- 0", "reply 6 garbled");
    assert_eq!(c.ask("/1 1").as_deref(), Some("@01 1 OK IDLE -- 0"));
    assert_eq!(h.received().len(), 7);
    assert_eq!(h.received()[1], "/1 1 home");
    h.stop();
}

#[test]
fn pty_slow_reply_arrives_late() {
    let h = spawn(Protocol::Esp300, &["slow:ms=2500,at=2"]);
    let mut c = Client::open(h.path());
    assert_eq!(c.ask("TE?").as_deref(), Some("0"));
    assert_eq!(c.ask("VE?"), None, "not within the first second");
    let mut late = None;
    for _ in 0..10 {
        if let Some(l) = c.line() {
            late = Some(l);
            break;
        }
    }
    assert!(String::from_utf8_lossy(&late.expect("the slow reply arrives")).starts_with("ESP300 Version"));
    h.stop();
}

#[test]
fn pty_client_can_close_and_reopen() {
    let h = spawn(Protocol::Esp300, &[]);
    for _ in 0..3 {
        let mut c = Client::open(h.path());
        assert_eq!(c.ask("1MO;1MO?").as_deref(), Some("1"));
    }
    h.stop();
}

#[test]
fn pty_disconnect_reconnect_and_restart_keep_the_state() {
    let dir = scratch("disconnect");
    let link = dir.join("stage");
    let state = dir.join("state.json");
    let mut cfg =
        EmulatorConfig::new(Protocol::Zaber, 1).with_faults(FaultPlan::parse(&["disconnect:at-move=2"]).unwrap());
    cfg.link = Some(link.clone());
    cfg.state_file = Some(state.clone());
    cfg.reconnect_after = Some(Duration::from_millis(100));
    let h = spawn_pty(cfg).unwrap();
    let mut c = Client::open(&link);
    assert_eq!(c.ask("/1 1 home").as_deref(), Some("@01 1 OK IDLE -- 0"));
    assert_eq!(c.ask("/1 1 move abs 1000").as_deref(), Some("@01 1 OK BUSY -- 0"));
    assert_eq!(c.ask("/1 1 move abs 2000"), None, "the pty closes instead of answering");
    drop(c);
    let deadline = Instant::now() + Duration::from_secs(5);
    while (h.disconnects() == 0 || !link.exists()) && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
    assert_eq!(h.disconnects(), 1);
    assert!(link.exists(), "link re-pointed after the reconnect");
    // (the kernel may hand out the same /dev/pts number again, so the path can be equal)
    assert!(h.current_path().exists());
    let mut c = Client::open(&link);
    assert_eq!(c.ask("/1 1 get pos").as_deref(), Some("@01 1 OK IDLE -- 1000"));
    drop(c);
    h.stop();
    assert!(!link.exists(), "link removed when the emulator stops");
    let saved: EmulatorState = serde_json::from_str(&std::fs::read_to_string(&state).unwrap()).unwrap();
    assert_eq!(
        saved.axes,
        vec![AxisState {
            pos: 1000.0,
            homed: true
        }]
    );
    // "emulator restart": a new process/thread with the same state file
    let mut cfg = EmulatorConfig::new(Protocol::Zaber, 1);
    cfg.state_file = Some(state);
    let h = spawn_pty(cfg).unwrap();
    let mut c = Client::open(h.path());
    assert_eq!(c.ask("/1 1 get pos").as_deref(), Some("@01 1 OK IDLE -- 1000"));
    drop(c);
    h.stop();
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn pty_disconnect_without_reconnect_ends_the_emulator() {
    let h = spawn(Protocol::Esp300, &["disconnect:at-move=1"]);
    let mut c = Client::open(h.path());
    c.send("1MO;1PA5");
    let deadline = Instant::now() + Duration::from_secs(5);
    while !h.is_finished() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(h.is_finished());
    assert!(!h.path().exists(), "slave path gone with the master");
    h.stop();
}

#[test]
fn config_is_validated() {
    for (axes, devices, upd) in [(0, 1, 1.0), (4, 1, 1.0), (1, 0, 1.0), (1, 1, 0.0), (1, 1, f64::NAN)] {
        let mut cfg = EmulatorConfig::new(Protocol::Esp300, axes);
        cfg.devices = devices;
        cfg.units_per_deg = upd;
        assert!(spawn_pty(cfg).is_err());
    }
}

/// `get encoder.pos` reads the load side of the mechanical error model while `get pos`
/// stays the step count: a target approached from below ends backlash/2 short, from above
/// backlash/2 past; without a model both readings agree.
#[test]
fn zaber_encoder_reads_the_load_side_of_the_error_model() {
    let mut cfg = EmulatorConfig::new(Protocol::Zaber, 1);
    cfg.mechanical = Some(crate::mechanics::MechanicalErrors {
        backlash_deg: 0.1,
        ..Default::default()
    });
    let mut z = controller(&cfg, None).unwrap();
    let t0 = Instant::now();
    let value = |r: String| -> i64 { r.rsplit(' ').next().unwrap().parse().unwrap() };
    one(z.as_mut(), "/1 1 home", t0);
    one(z.as_mut(), "/1 1 move abs 10000", t0);
    let t1 = secs(t0, 2.0);
    assert_eq!(value(one(z.as_mut(), "/1 1 get pos", t1)), 10_000);
    assert_eq!(value(one(z.as_mut(), "/1 1 get encoder.pos", t1)), 9_950);
    one(z.as_mut(), "/1 1 move abs 11000", t1);
    one(z.as_mut(), "/1 1 move abs 10000", secs(t0, 4.0));
    let t2 = secs(t0, 6.0);
    assert_eq!(value(one(z.as_mut(), "/1 1 get pos", t2)), 10_000);
    assert_eq!(value(one(z.as_mut(), "/1 1 get encoder.pos", t2)), 10_050);

    let mut ideal = zaber(1, &[]);
    one(ideal.as_mut(), "/1 1 home", t0);
    one(ideal.as_mut(), "/1 1 move abs 10000", t0);
    assert_eq!(value(one(ideal.as_mut(), "/1 1 get encoder.pos", t1)), 10_000);
}

#[test]
fn pty_hmp_answers_scpi_and_garbles_on_request() {
    let h = spawn(Protocol::Hmp4040, &["garble:at=3"]);
    let mut c = Client::open(h.path());
    assert_eq!(c.ask("*IDN?").as_deref(), Some(hmp::EMULATED_IDN));
    assert_eq!(
        c.ask("INST:NSEL 1;APPL 12,10;OUTP:SEL 1;OUTP:GEN 1;MEAS:VOLT?")
            .as_deref(),
        Some("12.000")
    );
    c.send("MEAS:CURR?");
    assert_eq!(
        c.line().unwrap(),
        faults::garble(b"8.3333"),
        "reply to command 3 garbled"
    );
    assert_eq!(c.ask("BOGUS?"), None, "an unknown header is not answered");
    assert_eq!(c.ask("SYST:ERR?").as_deref(), Some("-113,\"Undefined header\""));
    h.stop();
}

#[test]
fn hmp_rejects_motion_faults_and_bad_lamps() {
    let cfg = EmulatorConfig::new(Protocol::Hmp4040, 4).with_faults(FaultPlan::parse(&["stall:at-move=1"]).unwrap());
    let e = controller(&cfg, None).err().unwrap().to_string();
    assert!(e.contains("stall") && e.contains("garble"), "{e}");
    let mut cfg = EmulatorConfig::new(Protocol::Hmp4040, 5);
    assert!(controller(&cfg, None).is_err(), "an HMP4040 has 4 channels");
    cfg.axes = 4;
    cfg.lamp.cold_resistance_ohm = 2.0;
    let e = controller(&cfg, None).err().unwrap().to_string();
    assert!(e.contains("cold resistance"), "{e}");
}
