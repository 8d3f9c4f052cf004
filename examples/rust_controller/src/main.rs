//! An ambhil controller in Rust, written from docs/protocol.md (walk-through: docs/controllers.md).
//!
//! It takes the controller's role of one run: reads the discrete law from RunMeta's `controller`
//! object (no scene parser), pairs with the plant, answers every SensorSample with one
//! CurrentCommand and reproduces the built-in controller's currents bit for bit.
//!
//! ```text
//! rust_controller --run-id ID --connect tcp/127.0.0.1:7447 [--listen EP] [--start-timeout S]
//!                 [--sample-timeout S]
//! ```
//! Exit 0 after the plant's RUN_END (whatever its reason: a plant fault is the plant's to report),
//! 1 on a fault of its own (plant gone without RUN_END, pairing refused, bad RunMeta), 2 on bad
//! arguments.

use std::collections::BTreeSet;
use std::process::ExitCode;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use zenoh::bytes::Encoding;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::sample::SampleKind;
use zenoh::Wait;

const VERSION: u16 = 2;
const SEQ_WINDOW: i64 = 1 << 16; // protocol §5.1: a seq > last + SEQ_WINDOW is rejected
const MAX_AXES: usize = 64;
const PEER_ID_LEN: usize = 16;
const ENCAP: [u8; 4] = [0, 1, 0, 0];

// Event kinds (docs/protocol.md §3)
const EV_INFO: u16 = 0;
const EV_RUN_END: u16 = 2;
const EV_FAULT: u16 = 3;
const EV_REJECTED: u16 = 4;
const EV_DUPLICATE: u16 = 5;
const EV_GAP: u16 = 6;

type Res<T> = Result<T, String>;

// ------------------------------------------------------------------------------------ arguments
struct Args {
    run_id: String,
    connect: Vec<String>,
    listen: Vec<String>,
    start_timeout: f64,
    sample_timeout: f64,
}

fn parse_args() -> Res<Args> {
    let mut a = Args { run_id: String::new(), connect: vec![], listen: vec![],
                       start_timeout: 30.0, sample_timeout: 300.0 };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut val = || it.next().ok_or_else(|| format!("{flag}: missing value"));
        match flag.as_str() {
            "--run-id" => a.run_id = val()?,
            "--connect" => a.connect.push(val()?),
            "--listen" => a.listen.push(val()?),
            "--start-timeout" | "--sample-timeout" => {
                let v = val()?;
                let s: f64 = v.parse().ok().filter(|s: &f64| *s > 0.0)
                    .ok_or_else(|| format!("{flag}: expected a positive number of s, got {v:?}"))?;
                if flag == "--start-timeout" { a.start_timeout = s } else { a.sample_timeout = s }
            }
            "-h" | "--help" => {
                println!("rust_controller --run-id ID --connect ENDPOINT [--listen ENDPOINT] \
                          [--start-timeout S] [--sample-timeout S]");
                std::process::exit(0);
            }
            other => return Err(format!("unknown argument {other:?} (see --help)")),
        }
    }
    let ok = !a.run_id.is_empty() && a.run_id.len() <= 64
        && a.run_id.bytes().all(|c| c.is_ascii_alphanumeric() || b"_.-".contains(&c));
    if !ok {
        return Err(format!("--run-id: expected [A-Za-z0-9_.-]{{1,64}}, got {:?}", a.run_id));
    }
    if a.connect.is_empty() {
        return Err("--connect: the plant's endpoint is required, e.g. tcp/127.0.0.1:7447".into());
    }
    if a.listen.is_empty() {
        a.listen.push("tcp/127.0.0.1:0".into()); // so gossip can link the recorder to us
    }
    Ok(a)
}

// ------------------------------------------------------------------------------------ the law
/// One first-order discrete block: x' = a x + b u, y = c x + d u.
#[derive(Clone, Copy, Debug)]
struct Block { a: f64, b: f64, c: f64, d: f64 }

/// The discrete per-axis law of RunMeta `controller` (docs/protocol.md §5.2).
struct Law {
    sensor: Block, integral: Block, derivative: Block, amplifier: Block,
    kp: f64, ilim: f64, ulim: f64, anti_windup: bool, nd: usize, i_op: Vec<f64>,
}

/// Controller state: per axis [sensor, integrator, derivative, amplifier], the delay line.
struct State { x: Vec<[f64; 4]>, line: Vec<f64>, k: usize }

fn num(v: &serde_json::Value, key: &str) -> Res<f64> {
    v.get(key).and_then(|x| x.as_f64()).filter(|x| x.is_finite())
        .ok_or_else(|| format!("RunMeta controller.{key}: missing or not a finite number"))
}

fn limit(v: &serde_json::Value, key: &str) -> Res<f64> {
    match v.get(key) {
        Some(serde_json::Value::Null) => Ok(f64::INFINITY), // JSON has no infinity: null = none
        _ => num(v, key),
    }
}

impl Law {
    fn from_meta(meta: &serde_json::Value) -> Res<Law> {
        let c = meta.get("controller").ok_or(
            "RunMeta has no `controller` object (a recording or plant older than the \
             controller description, docs/protocol.md §5.2)")?;
        let law = c.get("law").and_then(|l| l.as_str()).unwrap_or("");
        if law != "sensor-pid-amplifier" {
            return Err(format!("RunMeta controller.law {law:?}: this example implements \
                                \"sensor-pid-amplifier\""));
        }
        let blk = |k: &str| -> Res<Block> {
            let b = c.get(k).ok_or(format!("RunMeta controller.{k}: missing"))?;
            Ok(Block { a: num(b, "a")?, b: num(b, "b")?, c: num(b, "c")?, d: num(b, "d")? })
        };
        let i_op: Vec<f64> = c.get("i_op").and_then(|v| v.as_array())
            .ok_or("RunMeta controller.i_op: missing")?
            .iter().map(|x| x.as_f64().filter(|x| x.is_finite())
                .ok_or("RunMeta controller.i_op: not a list of finite numbers".to_string()))
            .collect::<Res<_>>()?;
        let n = meta.get("n_axes").and_then(|v| v.as_u64()).unwrap_or(0) as usize;
        if i_op.is_empty() || i_op.len() > MAX_AXES || i_op.len() != n {
            return Err(format!("RunMeta: controller.i_op has {} axes, n_axes is {n}", i_op.len()));
        }
        let nd = c.get("delay_samples").and_then(|v| v.as_u64())
            .ok_or("RunMeta controller.delay_samples: missing")? as usize;
        Ok(Law {
            sensor: blk("sensor")?, integral: blk("integral")?, derivative: blk("derivative")?,
            amplifier: blk("amplifier")?, kp: num(c, "kp")?,
            ilim: limit(c, "current_limit")?, ulim: limit(c, "input_limit")?,
            anti_windup: c.get("anti_windup").and_then(|v| v.as_bool())
                .ok_or("RunMeta controller.anti_windup: missing")?,
            nd, i_op,
        })
    }

    fn n_axes(&self) -> usize { self.i_op.len() }

    /// Equilibrium at zero displacement with output i_op (docs/protocol.md §5.2, "start").
    fn initial_state(&self) -> State {
        let n = self.n_axes();
        let mut st = State { x: vec![[0.0; 4]; n], line: vec![0.0; n * self.nd], k: 0 };
        let (ia, am) = (&self.integral, &self.amplifier);
        for (a, &i0) in self.i_op.iter().enumerate() {
            if i0 == 0.0 {
                continue;
            }
            let amp_dc = am.d + if am.a != 1.0 { am.c * am.b / (1.0 - am.a) } else { 0.0 };
            let u = i0 / amp_dc;
            if ia.c != 0.0 {
                st.x[a][1] = u / ia.c;
            }
            if am.b != 0.0 {
                st.x[a][3] = am.b * u / (1.0 - am.a);
            }
            for j in 0..self.nd {
                st.line[a * self.nd + j] = i0;
            }
        }
        st
    }

    /// One sample, in the exact operation order of controller.discrete.controller_step.
    fn step(&self, st: &mut State, y: &[f64], cur: &mut [f64]) {
        let (s, ig, dv, am) = (&self.sensor, &self.integral, &self.derivative, &self.amplifier);
        for a in 0..y.len() {
            let x = &mut st.x[a];
            // sensor lag
            let xs = x[0];
            let ys = s.c * xs + s.d * y[a];
            x[0] = s.a * xs + s.b * y[a];
            let e = -ys;
            // PID: integral and filtered derivative
            let xi = x[1];
            let ui = ig.c * xi + ig.d * e;
            let xd = x[2];
            let ud = dv.c * xd + dv.d * e;
            x[2] = dv.a * xd + dv.b * e;
            let u = self.kp * e + ui + ud;
            let mut sat = false;
            let u_s = if u > self.ulim {
                sat = true;
                self.ulim
            } else if u < -self.ulim {
                sat = true;
                -self.ulim
            } else {
                u
            };
            // amplifier lag, current limit
            let xa = x[3];
            let mut i = am.c * xa + am.d * u_s;
            x[3] = am.a * xa + am.b * u_s;
            if i > self.ilim {
                i = self.ilim;
                sat = true;
            } else if i < -self.ilim {
                i = -self.ilim;
                sat = true;
            }
            // integrator with clamping anti-windup
            if !(sat && self.anti_windup && e * u > 0.0) {
                x[1] = ig.a * xi + ig.b * e;
            }
            // pure delay of nd samples
            if self.nd > 0 {
                let slot = a * self.nd + st.k;
                cur[a] = st.line[slot];
                st.line[slot] = i;
            } else {
                cur[a] = i;
            }
        }
        if self.nd > 0 {
            st.k = (st.k + 1) % self.nd;
        }
    }
}

// ------------------------------------------------------------------------------------ the wire
fn u16_at(b: &[u8], o: usize) -> u16 { u16::from_le_bytes(b[o..o + 2].try_into().unwrap()) }
fn u32_at(b: &[u8], o: usize) -> u32 { u32::from_le_bytes(b[o..o + 4].try_into().unwrap()) }
fn u64_at(b: &[u8], o: usize) -> u64 { u64::from_le_bytes(b[o..o + 8].try_into().unwrap()) }
fn f64_at(b: &[u8], o: usize) -> f64 { f64::from_le_bytes(b[o..o + 8].try_into().unwrap()) }

/// A rejected message: (reason code, text), docs/protocol.md §4.
type Reject = (&'static str, String);

fn check_header(b: &[u8], min: usize) -> Result<(), Reject> {
    if b.len() < min {
        return Err(("truncated", format!("{} bytes, need at least {min}", b.len())));
    }
    if b[..4] != ENCAP {
        return Err(("encapsulation", format!("header {:02x?}", &b[..4])));
    }
    if u16_at(b, 4) != VERSION {
        return Err(("version", format!("version {} != {VERSION}", u16_at(b, 4))));
    }
    Ok(())
}

/// SensorSample -> (seq, step, sim_time_ns); displacements into `y`. Its last 16 bytes are the
/// sender's peer id: one that is not `plant` is rejected (`peer`) before the rest is read.
fn decode_sensor(b: &[u8], plant: &[u8; PEER_ID_LEN], y: &mut [f64])
                 -> Result<(u64, u64, i64), Reject> {
    check_header(b, 52)?;
    let peer = &b[b.len() - PEER_ID_LEN..];
    if peer != plant {
        return Err(("peer", format!("sample seq {} from peer {}, not the paired plant {}",
                                    u64_at(b, 12), hex(peer), hex(plant))));
    }
    let n = u32_at(b, 44) as usize;
    if n > MAX_AXES {
        return Err(("oversize", format!("{n} axes > {MAX_AXES}")));
    }
    if n == 0 || n != y.len() {
        return Err(("axes", format!("{n} axes, the run has {}", y.len())));
    }
    if b.len() != 52 + 8 * n + PEER_ID_LEN {
        return Err(("length", format!("{} bytes != 52 + 8 x {n} + {PEER_ID_LEN}", b.len())));
    }
    for (a, v) in y.iter_mut().enumerate() {
        *v = f64_at(b, 52 + 8 * a);
        if !v.is_finite() {
            return Err(("nonfinite", format!("displacement[{a}] = {v}")));
        }
    }
    Ok((u64_at(b, 12), u64_at(b, 20), u64_at(b, 28) as i64))
}

/// CurrentCommand into `out`: the currents, then the sender's peer id `me` (no attachment).
fn encode_current(out: &mut Vec<u8>, seq: u64, step: u64, sim: i64, rx: i64, tx: i64, c: &[f64],
                  me: &[u8; PEER_ID_LEN]) {
    out.clear();
    out.extend_from_slice(&ENCAP);
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&[0; 6]);
    for v in [seq as i64, step as i64, sim, rx, tx] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&(c.len() as u32).to_le_bytes());
    out.extend_from_slice(&[0; 4]);
    for v in c {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(me);
}

/// CDR string at `o` (u32 length incl. NUL, aligned to 4 from the body start) -> (text, next).
fn cdr_string(b: &[u8], mut o: usize) -> Option<(String, usize)> {
    o += (4 - (o - 4) % 4) % 4;
    let n = u32_at(b.get(..o + 4)?, o) as usize;
    let s = b.get(o + 4..o + 4 + n)?;
    if n == 0 || s[n - 1] != 0 {
        return None;
    }
    Some((String::from_utf8(s[..n - 1].to_vec()).ok()?, o + 4 + n))
}

fn put_string(out: &mut Vec<u8>, s: &str) {
    while (out.len() - 4) % 4 != 0 {
        out.push(0);
    }
    out.extend_from_slice(&(s.len() as u32 + 1).to_le_bytes());
    out.extend_from_slice(s.as_bytes());
    out.push(0);
}

/// Event -> (kind, source, text).
fn decode_event(b: &[u8]) -> Option<(u16, String, String)> {
    check_header(b, 44).ok()?;
    let (src, o) = cdr_string(b, 44)?;
    let (text, _) = cdr_string(b, o)?;
    Some((u16_at(b, 6), src, text))
}

/// RunMeta -> its JSON object.
fn decode_meta(b: &[u8]) -> Res<serde_json::Value> {
    check_header(b, 44).map_err(|(r, t)| format!("RunMeta rejected: {r}: {t}"))?;
    let (text, _) = cdr_string(b, 44).ok_or("RunMeta rejected: string: bad string")?;
    let v: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| format!("RunMeta rejected: string: bad JSON: {e}"))?;
    if v.is_object() { Ok(v) } else { Err("RunMeta rejected: string: not a JSON object".into()) }
}

fn wall_ns() -> i64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_nanos() as i64).unwrap_or(0)
}

// ------------------------------------------------------------------------------------ events out
struct Events<'a> {
    publ: zenoh::pubsub::Publisher<'a>,
    me: [u8; PEER_ID_LEN],
    seq: u64,
    window: (Instant, u32, u64), // (start of the second, sent in it, suppressed)
}

impl Events<'_> {
    /// Event from `controller`, at most 200 per second (the excess is counted in the next one).
    fn emit(&mut self, kind: u16, text: &str, step: u64, sim: i64, force: bool) {
        let (t0, sent, supp) = &mut self.window;
        if t0.elapsed() >= Duration::from_secs(1) {
            *t0 = Instant::now();
            *sent = 0;
        }
        if !force && *sent >= 200 {
            *supp += 1;
            return;
        }
        *sent += 1;
        let text = if *supp > 0 { format!("{text} ({supp} events suppressed)") } else { text.into() };
        *supp = 0;
        let mut out = Vec::with_capacity(80 + text.len());
        out.extend_from_slice(&ENCAP);
        out.extend_from_slice(&VERSION.to_le_bytes());
        out.extend_from_slice(&kind.to_le_bytes());
        out.extend_from_slice(&[0; 4]);
        for v in [self.seq as i64, step as i64, sim, wall_ns()] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        put_string(&mut out, "controller");
        put_string(&mut out, &text);
        self.seq += 1;
        let _ = self.publ.put(out).attachment(self.me.to_vec()).wait();
    }
}

// ------------------------------------------------------------------------------------ peers
/// What the liveliness tokens of the run say about the plant, and the plant's RUN_END.
#[derive(Default)]
struct Peers {
    plant_starting: bool,
    plant_alive: bool,
    plant_seen: bool,  // was ready once
    plant_ids: BTreeSet<String>,
    paired: Option<[u8; PEER_ID_LEN]>,
    run_end: Option<String>, // RUN_END text from the paired plant
    foreign_ends: u64,       // RUN_END events from anyone else (ignored)
}

type Shared = Arc<(Mutex<Peers>, Condvar)>;

fn fresh_peer_id() -> Res<[u8; PEER_ID_LEN]> {
    use std::io::Read;
    let mut id = [0u8; PEER_ID_LEN];
    std::fs::File::open("/dev/urandom").and_then(|mut f| f.read_exact(&mut id))
        .map_err(|e| format!("cannot read /dev/urandom for the peer id: {e}"))?;
    if id == [0; PEER_ID_LEN] {
        id[0] = 1; // never all zero (docs/protocol.md §5.1)
    }
    Ok(id)
}

fn hex(b: &[u8]) -> String { b.iter().map(|x| format!("{x:02x}")).collect() }

// ------------------------------------------------------------------------------------ run
struct Summary { answered: u64, duplicates: u64, gaps: u64, rejected: u64, plant_end: String }

fn main() -> ExitCode {
    zenoh::init_log_from_env_or("error"); // RUST_LOG=zenoh=debug shows the links
    let args = match parse_args() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("rust_controller: error: {e}");
            return ExitCode::from(2);
        }
    };
    match run(&args) {
        Ok(s) => {
            println!("rust_controller: {} samples answered, {} duplicates, {} missing, {} rejected; \
                      plant ended: {}", s.answered, s.duplicates, s.gaps, s.rejected, s.plant_end);
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("rust_controller: error: run {}: {e}", args.run_id);
            ExitCode::from(1)
        }
    }
}

fn config(args: &Args) -> Res<zenoh::Config> {
    let mut c = zenoh::Config::default();
    let js = |v: &Vec<String>| serde_json::to_string(v).unwrap();
    // docs/protocol.md §1: the settings every node of a run must share
    for (k, v) in [("mode", "\"peer\"".to_string()),
                   ("scouting/multicast/enabled", "false".into()),
                   ("scouting/gossip/enabled", "true".into()),
                   ("transport/unicast/lowlatency", "true".into()),
                   ("transport/unicast/qos/enabled", "false".into()),
                   // a pool of 4 receive batches (zenoh's default, one, allocates and zeroes
                   // 64 KiB for each message; recommended, not required to agree)
                   ("transport/link/rx/buffer_size", (4 * 65535).to_string()),
                   ("listen/endpoints", js(&args.listen)),
                   ("connect/endpoints", js(&args.connect))] {
        c.insert_json5(k, &v).map_err(|e| format!("zenoh config {k}: {e}"))?;
    }
    Ok(c)
}

fn run(args: &Args) -> Res<Summary> {
    let root = format!("ambhil/{}", args.run_id);
    let session = zenoh::open(config(args)?).wait()
        .map_err(|e| format!("cannot open zenoh session (connect {:?}): {e}", args.connect))?;
    let zerr = |what: &str| { let w = what.to_string(); move |e: zenoh::Error| format!("{w}: {e}") };
    let lv = session.liveliness();
    let _starting = lv.declare_token(format!("{root}/starting/controller")).wait()
        .map_err(zerr("starting token"))?;
    // status/controller answers the current start-up step (protocol §2)
    let status = Arc::new(Mutex::new(String::from("controller: starting")));
    let st = status.clone();
    let _status_q = session.declare_queryable(format!("{root}/status/controller"))
        .callback(move |q| {
            let text = st.lock().unwrap().clone();
            let _ = q.reply(q.key_expr().clone(), text).wait();
        })
        .wait().map_err(zerr("status queryable"))?;
    let step = |text: &str| *status.lock().unwrap() = format!("controller: {text}");

    // subscriptions first, then the tokens (docs/protocol.md §5)
    let shared: Shared = Arc::new((Mutex::new(Peers::default()), Condvar::new()));
    let sh = shared.clone();
    let n_root = root.split('/').count();
    let _live = lv.declare_subscriber(format!("{root}/**")).history(true)
        .callback(move |s| {
            let key = s.key_expr().as_str().to_string();
            let parts: Vec<&str> = key.split('/').skip(n_root).collect();
            let put = s.kind() == SampleKind::Put;
            let (lock, cv) = &*sh;
            let mut p = lock.lock().unwrap();
            match parts.as_slice() {
                ["starting", "plant"] => p.plant_starting = put,
                ["alive", "plant"] => {
                    p.plant_alive = put;
                    p.plant_seen |= put;
                }
                ["peer", "plant", id] if id.len() == 2 * PEER_ID_LEN => {
                    if put { p.plant_ids.insert(id.to_string()); } else { p.plant_ids.remove(*id); }
                }
                _ => return,
            }
            cv.notify_all();
        })
        .wait().map_err(zerr("liveliness subscriber"))?;
    let sh = shared.clone();
    let _ev_sub = session.declare_subscriber(format!("{root}/events"))
        .callback(move |s| {
            if let Some((kind, src, text)) = decode_event(&s.payload().to_bytes()) {
                if kind == EV_RUN_END && (src == "plant" || src == "replay") {
                    // only the paired plant ends the run (its peer id attached)
                    let att = s.attachment().map(|a| a.to_bytes().to_vec());
                    let (lock, cv) = &*sh;
                    let mut p = lock.lock().unwrap();
                    if p.paired.is_some() && att.as_deref() == p.paired.as_ref().map(|x| &x[..]) {
                        p.run_end = Some(text);
                    } else {
                        p.foreign_ends += 1;
                    }
                    cv.notify_all();
                }
            }
        })
        .wait().map_err(zerr("events subscriber"))?;
    let meta_sub = session.declare_subscriber(format!("{root}/meta")).wait()
        .map_err(zerr("meta subscriber"))?;
    let sensors = session.declare_subscriber(format!("{root}/plant/sensors"))
        .with(zenoh::handlers::FifoChannel::new(1024)).wait()
        .map_err(zerr("sensors subscriber"))?;
    let currents = session.declare_publisher(format!("{root}/controller/currents"))
        .encoding(Encoding::APPLICATION_CDR).congestion_control(CongestionControl::Block)
        .priority(Priority::RealTime).express(true).wait()
        .map_err(zerr("currents publisher"))?;
    let ev_pub = session.declare_publisher(format!("{root}/events"))
        .encoding(Encoding::APPLICATION_CDR).congestion_control(CongestionControl::Block)
        .wait().map_err(zerr("events publisher"))?;
    let me = fresh_peer_id()?;
    let mut ev = Events { publ: ev_pub, me, seq: 0, window: (Instant::now(), 0, 0) };

    let _peer = lv.declare_token(format!("{root}/peer/controller/{}", hex(&me))).wait()
        .map_err(zerr("peer token"))?;
    let _alive = lv.declare_token(format!("{root}/alive/controller")).wait()
        .map_err(zerr("alive token"))?;
    ev.emit(EV_INFO, "rust_controller: ready; waiting for plant", 0, 0, true);
    step("ready; waiting for plant");
    eprintln!("rust_controller: ready (peer id {}); waiting for plant", hex(&me));

    // wait for the plant as long as it is present; pair with its single peer id
    let paired = wait_and_pair(&shared, &root, args.start_timeout)?;
    shared.0.lock().unwrap().paired = Some(paired);
    eprintln!("rust_controller: paired with plant {}", hex(&paired));
    let plant_gone = || {
        let p = shared.0.lock().unwrap();
        p.plant_seen && !p.plant_alive && p.run_end.is_none()
    };
    while !currents.matching_status().wait().map(|m| m.matching()).unwrap_or(false) {
        if plant_gone() {
            return Err("plant lost (liveliness) before start".into());
        }
        std::thread::sleep(Duration::from_millis(5));
    }

    // RunMeta (from the paired plant) comes before sample 0: the law, n axes
    let meta = loop {
        match meta_sub.recv_timeout(Duration::from_millis(50)) {
            Ok(Some(s)) => {
                if s.attachment().map(|a| a.to_bytes()[..] == paired[..]).unwrap_or(false) {
                    break decode_meta(&s.payload().to_bytes())?;
                }
                eprintln!("rust_controller: RunMeta not from the paired plant ignored");
            }
            Ok(None) => {
                if plant_gone() {
                    return Err("plant lost (liveliness) before its RunMeta".into());
                }
            }
            Err(e) => return Err(format!("meta subscriber closed: {e}")),
        }
    };
    let law = Law::from_meta(&meta)?;
    let n = law.n_axes();
    let mut st = law.initial_state();
    ev.emit(EV_INFO, &format!("rust_controller: running, {n} axes"), 0, 0, true);
    step("running");

    let (mut y, mut cur) = (vec![0.0; n], vec![0.0; n]);
    let mut out = Vec::with_capacity(60 + 8 * n + PEER_ID_LEN);
    let mut last: i64 = -1;
    let mut s = Summary { answered: 0, duplicates: 0, gaps: 0, rejected: 0, plant_end: String::new() };
    let mut t_last = Instant::now();
    loop {
        let smp = match sensors.recv_timeout(Duration::from_millis(50)) {
            Ok(Some(smp)) => smp,
            Ok(None) => {
                // between samples: the end conditions
                let (end, lost) = {
                    let p = shared.0.lock().unwrap();
                    (p.run_end.clone(), p.plant_seen && !p.plant_alive)
                };
                if let Some(text) = end {
                    s.plant_end = text;
                    return Ok(s);
                }
                if lost {
                    // RUN_END may still be in flight on the events subscriber
                    std::thread::sleep(Duration::from_millis(20));
                    if let Some(text) = shared.0.lock().unwrap().run_end.clone() {
                        s.plant_end = text;
                        return Ok(s);
                    }
                    let msg = format!("plant lost (liveliness) after {} samples", s.answered);
                    ev.emit(EV_FAULT, &msg, 0, 0, true);
                    return Err(msg);
                }
                if s.answered > 0 && t_last.elapsed().as_secs_f64() > args.sample_timeout {
                    let msg = format!("plant timeout: no sample for {} s after seq {last}",
                                      args.sample_timeout);
                    ev.emit(EV_FAULT, &msg, 0, 0, true);
                    return Err(msg);
                }
                continue;
            }
            Err(e) => return Err(format!("sensors subscriber closed: {e}")),
        };
        let t_rx = wall_ns();
        let data = smp.payload().to_bytes();
        let (seq, step, sim) = match decode_sensor(&data, &paired, &mut y) {
            Err(("peer", text)) => {
                s.rejected += 1;
                ev.emit(EV_REJECTED, &format!("peer: {text}"), 0, 0, false);
                continue;
            }
            Err((reason, text)) => {
                s.rejected += 1;
                ev.emit(EV_REJECTED, &format!("{reason}: sensor sample rejected: {text}"), 0, 0, false);
                continue;
            }
            Ok(h) => h,
        };
        let sq = seq as i64; // seq >= 2^63 reads negative: stale, never answered
        if sq <= last {
            s.duplicates += 1;
            ev.emit(EV_DUPLICATE, &format!("duplicate/stale sample seq {seq} (last {last}) ignored"),
                    step, sim, false);
            continue;
        }
        if sq > last + SEQ_WINDOW {
            s.rejected += 1;
            ev.emit(EV_REJECTED, &format!("sequence: sensor sample rejected: seq {seq} beyond the \
                                           window (last {last} + {SEQ_WINDOW})"), step, sim, false);
            continue;
        }
        if sq != last + 1 {
            s.gaps += (sq - last - 1) as u64;
            ev.emit(EV_GAP, &format!("samples {}..{} missing", last + 1, sq - 1), step, sim, false);
        }
        last = sq;
        law.step(&mut st, &y, &mut cur);
        if let Some(a) = cur.iter().position(|c| !c.is_finite()) {
            let msg = format!("controller produced non-finite currents at step {step}: axis {a} = {}",
                              cur[a]);
            ev.emit(EV_FAULT, &msg, step, sim, true);
            return Err(msg);
        }
        encode_current(&mut out, seq, step, sim, t_rx, wall_ns(), &cur, &me);
        currents.put(out.clone()).wait()
            .map_err(|e| format!("publishing currents: {e}"))?;
        s.answered += 1;
        t_last = Instant::now();
    }
}

/// Wait for `alive/plant` as long as the plant is present (start_timeout counts absence only),
/// then pair with the single `peer/plant/<id>` token (docs/protocol.md §5.1).
fn wait_and_pair(shared: &Shared, root: &str, start_timeout: f64) -> Res<[u8; PEER_ID_LEN]> {
    let (lock, cv) = &**shared;
    let mut p = lock.lock().unwrap();
    let mut absent = Duration::ZERO;
    let mut ready_at: Option<Instant> = None;
    let mut first_id: Option<Instant> = None;
    loop {
        if p.plant_alive && !p.plant_ids.is_empty() {
            // let a second announcement already on its way arrive (two plants are seen as two)
            if first_id.get_or_insert_with(Instant::now).elapsed() >= Duration::from_millis(20) {
                break;
            }
        }
        if p.plant_seen && !p.plant_alive {
            return Err("plant went away before the run started".into());
        }
        let t = Instant::now();
        if p.plant_alive {
            // ready but no peer id yet: the token may still be in flight, not for long
            let t0 = *ready_at.get_or_insert(t);
            if t0.elapsed().as_secs_f64() > start_timeout {
                return Err(format!("plant is ready but announced no peer id ({root}/peer/plant/*) \
                                    within {start_timeout} s; does it implement pairing?"));
            }
        } else if !p.plant_starting && absent.as_secs_f64() > start_timeout {
            return Err(format!("no plant for {start_timeout} s ({root}/starting/plant absent)"));
        }
        let present = p.plant_starting || p.plant_alive;
        p = cv.wait_timeout(p, Duration::from_millis(10)).unwrap().0;
        if !present {
            absent += t.elapsed();
        }
    }
    if p.plant_ids.len() > 1 {
        let ids: Vec<&str> = p.plant_ids.iter().map(|s| s.as_str()).collect();
        return Err(format!("{} plant processes announce a peer id ({}); refusing to pair with any \
                            (another process is using this run id)", ids.len(), ids.join(", ")));
    }
    let h = p.plant_ids.iter().next().unwrap();
    let mut id = [0u8; PEER_ID_LEN];
    for (i, b) in id.iter_mut().enumerate() {
        *b = u8::from_str_radix(&h[2 * i..2 * i + 2], 16)
            .map_err(|_| format!("plant peer id {h:?} is not hex"))?;
    }
    Ok(id)
}

#[cfg(test)]
mod tests {
    use super::*;

    const PLANT: [u8; PEER_ID_LEN] = [0xa5; PEER_ID_LEN];

    /// A SensorSample of `y` with version `ver`, then `extra` bytes and the peer id `tail`.
    fn sample(ver: u16, seq: u64, y: &[f64], extra: usize, tail: &[u8]) -> Vec<u8> {
        let mut b = ENCAP.to_vec();
        b.extend_from_slice(&ver.to_le_bytes());
        b.extend_from_slice(&[0; 6]);
        for v in [seq as i64, 6, 7, 8] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&(y.len() as u32).to_le_bytes());
        b.extend_from_slice(&[0; 4]);
        for v in y {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend(std::iter::repeat(0).take(extra));
        b.extend_from_slice(tail);
        b
    }

    #[test]
    fn current_command_v2_layout() {
        let me: [u8; PEER_ID_LEN] = core::array::from_fn(|i| i as u8 + 1);
        let mut out = Vec::new();
        for n in [1usize, 3, 6] {
            let c: Vec<f64> = (0..n).map(|a| 0.5 * (a + 1) as f64).collect();
            encode_current(&mut out, 7, 8, 9, 10, 11, &c, &me);
            assert_eq!(out.len(), 76 + 8 * n);
            assert_eq!(out[..6], [0, 1, 0, 0, 2, 0]);
            assert_eq!(out[60 + 8 * n..], me);
            assert_eq!((u64_at(&out, 12), u64_at(&out, 20), u32_at(&out, 52)), (7, 8, n as u32));
            assert_eq!(f64_at(&out, 60 + 8 * (n - 1)), c[n - 1]);
        }
    }

    #[test]
    fn sensor_sample_v2_checks() {
        let y3 = [0.001, 0.002, 0.003];
        let mut y = [0.0; 3];
        let ok = sample(2, 5, &y3, 0, &PLANT);
        assert_eq!(ok.len(), 52 + 24 + 16);
        assert_eq!(decode_sensor(&ok, &PLANT, &mut y), Ok((5, 6, 7)));
        assert_eq!(y, y3);
        let reason = |b: &[u8]| decode_sensor(b, &PLANT, &mut [0.0; 3]).unwrap_err();
        let (r, t) = reason(&sample(2, 5, &y3, 0, &[0x11; PEER_ID_LEN]));
        assert_eq!(r, "peer");
        assert!(t.contains(&"11".repeat(PEER_ID_LEN)) && t.contains(&hex(&PLANT)), "{t}");
        assert_eq!(reason(&ok[..ok.len() - PEER_ID_LEN]).0, "peer"); // version-1 layout, no tail
        assert_eq!(reason(&sample(1, 5, &y3, 0, &PLANT)).0, "version");
        assert_eq!(reason(&sample(1, 5, &y3, 0, &[0x11; PEER_ID_LEN])).0, "version");
        assert_eq!(reason(&sample(2, 5, &y3, 8, &PLANT)).0, "length");
        assert_eq!(reason(&sample(2, 5, &[0.0; 4], 0, &PLANT)).0, "axes");
        assert_eq!(reason(&sample(2, 5, &[0.0; 4], 0, &[0x11; PEER_ID_LEN])).0, "peer");
        assert_eq!(reason(&sample(2, 5, &[0.0, f64::NAN, 0.0], 0, &PLANT)).0, "nonfinite");
        assert_eq!(reason(&ok[..40]).0, "truncated");
    }
}
