//! An ambhil controller in Rust, written from docs/protocol.md (walk-through: docs/controllers.md).
//!
//! It takes the controller's role of one run: proves that it holds the run's secret, pairs with
//! the plant whose RunMeta proves the same (protocol 3, §5.3), reads the discrete law from
//! RunMeta's `controller` object (no scene parser), answers every authenticated SensorSample
//! with one sealed CurrentCommand and reproduces the built-in controller's currents bit for bit.
//!
//! ```text
//! rust_controller --run-id ID --connect tcp/127.0.0.1:7447 [--listen EP] [--key-file FILE]
//!                 [--insecure] [--start-timeout S] [--sample-timeout S]
//! rust_controller --selftest-vectors tests/fixtures/auth_vectors.json
//! ```
//! The secret: `--key-file FILE`, else the file named by $AMBHIL_KEY_FILE, else none (an
//! unauthenticated run: the all-zero secret; listening beyond loopback then needs --insecure).
//! Exit 0 after the plant's RUN_END (whatever its reason: a plant fault is the plant's to report),
//! 1 on a fault of its own (plant gone without RUN_END, bad RunMeta), 2 on bad arguments or an
//! unusable key file.
//!
//! Files: `auth.rs` keys and MACs, `wire.rs` the messages, `events.rs` the events (ours out, the
//! plant's judged), `law.rs` the law, `args.rs` the command line, `vectors.rs` the self-test
//! against the shared test vectors (tests/fixtures/auth_vectors.json).

mod args;
mod auth;
mod events;
mod law;
mod vectors;
mod wire;

use std::collections::{BTreeMap, VecDeque};
use std::process::ExitCode;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use zenoh::bytes::Encoding;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::sample::SampleKind;
use zenoh::Wait;

use args::{parse_args, Args};
use auth::{hex, pair_proof, random, run_key, session_key, topic_key, verify_attachment, Id, Key,
           ATTACH_LEN, ID_LEN, KEY_LEN, NONCE_LEN};
use events::{judge_event, Events, Paired, Peers, Shared};
use law::Law;
use wire::{decode_meta, decode_sensor, encode_current, TRAILER};

const SEQ_WINDOW: i64 = 1 << 16; // protocol §5.3: a seq > last + SEQ_WINDOW is rejected
pub const MAX_AXES: usize = 64;
const CANDIDATES: usize = 64; // pairing challenges remembered

// Event kinds (docs/protocol.md §3)
pub const EV_INFO: u16 = 0;
const EV_FAULT: u16 = 3;
const EV_REJECTED: u16 = 4;
const EV_DUPLICATE: u16 = 5;
const EV_GAP: u16 = 6;

pub type Res<T> = Result<T, String>;

pub fn wall_ns() -> i64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_nanos() as i64).unwrap_or(0)
}

type Candidates = Arc<Mutex<VecDeque<(Id, [u8; NONCE_LEN], [u8; NONCE_LEN])>>>;

/// The run's secret and what derives from it before pairing.
struct Secret { secret: Key, run: String, k_run: Key, mode: &'static str }

// ------------------------------------------------------------------------------------ run
struct Summary {
    answered: u64, duplicates: u64, gaps: u64, plant_end: String,
    rejected: BTreeMap<&'static str, u64>, foreign_events: u64, strangers: Vec<String>,
}

impl Summary {
    fn reject(&mut self, ev: &mut Events, reason: &'static str, text: &str, step: u64, sim: i64) {
        *self.rejected.entry(reason).or_default() += 1;
        ev.emit(EV_REJECTED, text, step, sim, false);
    }
    fn auth_line(&self, mode: &str) -> String {
        format!("auth {mode}; rejected {:?}, foreign events {}, strangers {:?}", self.rejected,
                self.foreign_events, self.strangers)
    }
}

fn main() -> ExitCode {
    let argv: Vec<String> = std::env::args().collect();
    if argv.len() == 3 && argv[1] == "--selftest-vectors" {
        return match vectors::selftest(&argv[2]) {
            Ok(out) => {
                println!("{out}");
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("rust_controller: error: {e}");
                ExitCode::from(1)
            }
        };
    }
    zenoh::init_log_from_env_or("error"); // RUST_LOG=zenoh=debug shows the links
    let fail = |e: String| {
        eprintln!("rust_controller: error: {e}");
        ExitCode::from(2)
    };
    let args = match parse_args() {
        Ok(a) => a,
        Err(e) => return fail(e),
    };
    let secret = match args.key_file.as_deref().map(auth::read_key_file).transpose() {
        Ok(s) => s,
        Err(e) => return fail(e),
    };
    if let (None, false, Some(ep)) = (secret, args.insecure, args.listen.iter().find(|e| !auth::is_loopback(e))) {
        return fail(format!("--listen {ep} is not loopback: give --key-file FILE (ambhil key FILE), or \
                             --insecure to run unauthenticated"));
    }
    let mode = if secret.is_some() { "key" } else if args.insecure { "insecure" } else { "none" };
    let secret = secret.unwrap_or([0; KEY_LEN]);
    let sec = Secret { secret, k_run: run_key(&secret, &args.run_id), run: args.run_id.clone(), mode };
    let mut s = Summary { answered: 0, duplicates: 0, gaps: 0, plant_end: String::new(),
                          rejected: BTreeMap::new(), foreign_events: 0, strangers: vec![] };
    let r = run(&args, &sec, &mut s);
    eprintln!("rust_controller: {}", s.auth_line(mode));
    match r {
        Ok(()) => {
            println!("rust_controller: {} samples answered, {} duplicates, {} missing, {} rejected; \
                      plant ended: {}", s.answered, s.duplicates, s.gaps, s.rejected.values().sum::<u64>(),
                     s.plant_end);
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

fn run(args: &Args, sec: &Secret, s: &mut Summary) -> Res<()> {
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
    let shared: Shared = Arc::new((Mutex::new(Peers { last_event_seq: -1, ..Default::default() }), Condvar::new()));
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
                _ => return,
            }
            cv.notify_all();
        })
        .wait().map_err(zerr("liveliness subscriber"))?;
    // only the plant's events concern a controller
    let sh = shared.clone();
    let _ev_sub = session.declare_subscriber(format!("{root}/events/plant"))
        .callback(move |smp| {
            let att = smp.attachment().map(|a| a.to_bytes().to_vec());
            let (lock, cv) = &*sh;
            judge_event(&mut lock.lock().unwrap(), &smp.payload().to_bytes(), att.as_deref());
            cv.notify_all();
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
    let ev_pub = session.declare_publisher(format!("{root}/events/controller"))
        .encoding(Encoding::APPLICATION_CDR).congestion_control(CongestionControl::Block)
        .wait().map_err(zerr("events publisher"))?;
    let mut me: Id = random()?;
    me[0] |= (me == [0; ID_LEN]) as u8; // never all zero (docs/protocol.md §5.1)
    let mut ev = Events { publ: ev_pub, me, key: topic_key(&sec.k_run, "events/controller"), seq: 0,
                          window: (Instant::now(), 0, 0) };

    // the pairing queryable before the peer token: whoever sees the token may challenge us;
    // each answer (a fresh nonce_r) is remembered as a candidate session
    let candidates: Candidates = Arc::new(Mutex::new(VecDeque::new()));
    let (cands, k_run) = (candidates.clone(), sec.k_run);
    let _pair_q = session.declare_queryable(format!("{root}/pair/controller/{}", hex(&me)))
        .callback(move |q| {
            let Some(raw) = q.payload().map(|p| p.to_bytes().to_vec()) else { return };
            if raw.len() != ID_LEN + NONCE_LEN {
                return;
            }
            let (Ok(nonce_r), Ok(challenger), Ok(nonce_q)) =
                (random::<NONCE_LEN>(), Id::try_from(&raw[..ID_LEN]), raw[ID_LEN..].try_into()) else { return };
            {
                let mut c = cands.lock().unwrap();
                if c.len() == CANDIDATES {
                    c.pop_front();
                }
                c.push_back((challenger, nonce_q, nonce_r));
            }
            let mut reply = nonce_r.to_vec();
            reply.extend_from_slice(&pair_proof(&k_run, "controller", &me, &challenger, &nonce_q, &nonce_r));
            let _ = q.reply(q.key_expr().clone(), reply).wait();
        })
        .wait().map_err(zerr("pairing queryable"))?;
    let _peer = lv.declare_token(format!("{root}/peer/controller/{}", hex(&me))).wait()
        .map_err(zerr("peer token"))?;
    let _alive = lv.declare_token(format!("{root}/alive/controller")).wait()
        .map_err(zerr("alive token"))?;
    ev.emit(EV_INFO, "rust_controller: ready; waiting for plant", 0, 0, true);
    step("ready; waiting for plant");
    eprintln!("rust_controller: ready (peer id {}, auth {}); waiting for plant", hex(&me), sec.mode);

    // wait for the plant as long as it is present; pair with the RunMeta that proves a candidate
    // samples that come before pairing wait here (read, so that a stranger's flood cannot fill
    // the FIFO and block zenoh's receive thread); checked once paired
    let mut early: VecDeque<(i64, Vec<u8>)> = VecDeque::new();
    let keep_early = |early: &mut VecDeque<(i64, Vec<u8>)>| {
        while let Ok(Some(smp)) = sensors.try_recv() {
            if early.len() < 1024 {
                early.push_back((wall_ns(), smp.payload().to_bytes().to_vec()));
            }
        }
    };
    let (plant, k_s, meta) = wait_and_pair(&shared, &meta_sub, sec, &me, &candidates, &mut ev, s, args,
                                           &mut || keep_early(&mut early))?;
    ev.key = topic_key(&k_s, "events/controller");
    {
        let (lock, cv) = &*shared;
        let mut p = lock.lock().unwrap();
        p.paired = Some(Paired { plant, events: topic_key(&k_s, "events/plant"),
                                 events_run: topic_key(&sec.k_run, "events/plant") });
        for (payload, att) in std::mem::take(&mut p.early) {
            judge_event(&mut p, &payload, att.as_deref());
        }
        cv.notify_all();
    }
    eprintln!("rust_controller: paired with plant {} (auth {})", hex(&plant),
              meta["auth"]["mode"].as_str().unwrap_or("?"));
    let plant_gone = || {
        let p = shared.0.lock().unwrap();
        p.plant_seen && !p.plant_alive && p.run_end.is_none()
    };
    while !currents.matching_status().wait().map(|m| m.matching()).unwrap_or(false) {
        if plant_gone() {
            return Err("plant lost (liveliness) before start".into());
        }
        keep_early(&mut early);
        std::thread::sleep(Duration::from_millis(5));
    }
    let law = Law::from_meta(&meta)?;
    let n = law.n_axes();
    let mut st = law.initial_state();
    ev.emit(EV_INFO, &format!("rust_controller: running, {n} axes"), 0, 0, true);
    step("running");

    let (k_sensors, k_currents) = (topic_key(&k_s, "plant/sensors"), topic_key(&k_s, "controller/currents"));
    let meta_key = topic_key(&k_s, "meta");
    let (mut y, mut cur) = (vec![0.0; n], vec![0.0; n]);
    let mut out = Vec::with_capacity(60 + 8 * n + TRAILER);
    let mut last: i64 = -1; // last answered seq of the confirmed stream
    let mut jump: Option<i64> = None; // a seq that jumped ahead, not yet confirmed (§5.3)
    let mut t_last = Instant::now();
    loop {
        // events rejected by the callback; RunMeta after pairing (a repeat, or someone else's)
        let rejects = std::mem::take(&mut shared.0.lock().unwrap().rejects);
        for (reason, text) in rejects {
            s.foreign_events += 1;
            s.reject(&mut ev, reason, &text, 0, 0);
        }
        while let Ok(Some(m)) = meta_sub.try_recv() {
            let att = m.attachment().map(|a| a.to_bytes().to_vec());
            if !verify_attachment(&meta_key, &m.payload().to_bytes(), att.as_deref(), &plant) {
                s.reject(&mut ev, "auth", "RunMeta rejected: auth: not the paired plant's", 0, 0);
            }
        }
        let next = match early.pop_front() {
            Some(x) => Ok(Some(x)),
            None => sensors.recv_timeout(Duration::from_millis(50))
                .map(|o| o.map(|smp| (wall_ns(), smp.payload().to_bytes().to_vec()))),
        };
        let (t_rx, data) = match next {
            Ok(Some(x)) => x,
            Ok(None) => {
                // between samples: the end conditions
                let (end, lost) = {
                    let p = shared.0.lock().unwrap();
                    (p.run_end.clone(), p.plant_seen && !p.plant_alive)
                };
                if let Some(text) = end {
                    s.plant_end = text;
                    return Ok(());
                }
                if lost {
                    // RUN_END may still be in flight on the events subscriber
                    std::thread::sleep(Duration::from_millis(20));
                    if let Some(text) = shared.0.lock().unwrap().run_end.clone() {
                        s.plant_end = text;
                        return Ok(());
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
        let (seq, step, sim) = match decode_sensor(&data, &plant, &k_sensors, &mut y) {
            Err((reason, text)) => {
                s.reject(&mut ev, reason, &format!("sensor sample rejected: {reason}: {text}"), 0, 0);
                continue;
            }
            Ok(h) => h,
        };
        // a jump ahead is answered but moves `last` only once the next sample confirms it, so
        // one message cannot make the genuine stream stale (protocol §5.3)
        let sq = seq as i64; // seq >= 2^63 reads negative: stale, never answered
        if sq == last + 1 || jump.is_some_and(|j| sq == j + 1) {
            last = sq;
            jump = None;
        } else if sq <= last || jump == Some(sq) {
            s.duplicates += 1;
            ev.emit(EV_DUPLICATE, &format!("duplicate/stale sample seq {seq} (last {last}) ignored"),
                    step, sim, false);
            continue;
        } else if sq > last + SEQ_WINDOW {
            s.reject(&mut ev, "sequence", &format!("sensor sample rejected: sequence: seq {seq} beyond the \
                                                    window (last {last} + {SEQ_WINDOW})"), step, sim);
            continue;
        } else {
            jump = Some(sq);
            s.gaps += (sq - last - 1) as u64;
            ev.emit(EV_GAP, &format!("samples {}..{} missing", last + 1, sq - 1), step, sim, false);
        }
        let restart = {
            let mut p = shared.0.lock().unwrap();
            let before = p.restarts.len();
            p.restarts.retain(|&at| at > step);
            p.restarts.len() != before
        };
        if restart {
            // reset before the first sample at or after that step (protocol §5, controller rule)
            st = law.initial_state();
            ev.emit(EV_INFO, &format!("controller restarted (state reset) before step {step}"), step, sim, true);
        }
        law.step(&mut st, &y, &mut cur);
        if let Some(a) = cur.iter().position(|c| !c.is_finite()) {
            let msg = format!("controller produced non-finite currents at step {step}: axis {a} = {}",
                              cur[a]);
            ev.emit(EV_FAULT, &msg, step, sim, true);
            return Err(msg);
        }
        encode_current(&mut out, seq, step, sim, t_rx, wall_ns(), &cur, &me, &k_currents);
        currents.put(out.clone()).wait()
            .map_err(|e| format!("publishing currents: {e}"))?;
        s.answered += 1;
        t_last = Instant::now();
    }
}

/// Wait for the plant as long as it is present (start_timeout counts absence only) and pair with
/// the first RunMeta whose attached id and `auth` nonces are one of our candidate sessions and
/// whose MAC verifies under that session's K_s (docs/protocol.md §5.3). Any other RunMeta is
/// rejected (`auth`) and its sender named a stranger: it neither pairs nor blocks.
#[allow(clippy::too_many_arguments)]
fn wait_and_pair(shared: &Shared, meta_sub: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
                 sec: &Secret, me: &Id, candidates: &Candidates, ev: &mut Events, s: &mut Summary, args: &Args,
                 keep_early: &mut dyn FnMut()) -> Res<(Id, Key, serde_json::Value)> {
    let mut absent = Duration::ZERO;
    loop {
        {
            let p = shared.0.lock().unwrap();
            if p.plant_seen && !p.plant_alive {
                return Err("plant went away before the run started".into());
            }
            if !p.plant_starting && !p.plant_alive && absent.as_secs_f64() > args.start_timeout {
                return Err(format!("no plant for {} s (ambhil/{}/starting/plant absent)", args.start_timeout,
                                   sec.run));
            }
        }
        keep_early();
        let t = Instant::now();
        let m = match meta_sub.recv_timeout(Duration::from_millis(10)) {
            Ok(Some(m)) => m,
            Ok(None) => {
                let p = shared.0.lock().unwrap();
                if !p.plant_starting && !p.plant_alive {
                    absent += t.elapsed();
                }
                continue;
            }
            Err(e) => return Err(format!("meta subscriber closed: {e}")),
        };
        let (payload, att) = (m.payload().to_bytes().to_vec(), m.attachment().map(|a| a.to_bytes().to_vec()));
        let Some(pid) = att.as_deref().filter(|a| a.len() == ATTACH_LEN).map(|a| Id::try_from(&a[..ID_LEN]).unwrap())
        else {
            s.reject(ev, "auth", "RunMeta rejected: auth: no peer id and MAC attached", 0, 0);
            continue;
        };
        let found = candidates.lock().unwrap().iter().rev().find_map(|(c, nq, nr)| {
            let k_s = session_key(&sec.secret, &sec.run, &pid, me, nq, nr);
            (*c == pid && verify_attachment(&topic_key(&k_s, "meta"), &payload, att.as_deref(), &pid))
                .then_some((k_s, *nq, *nr))
        });
        let Some((k_s, nq, nr)) = found else {
            if !s.strangers.contains(&hex(&pid)) {
                s.strangers.push(hex(&pid));
                eprintln!("rust_controller: stranger {} sent a RunMeta that fails the pairing proof (no key)",
                          hex(&pid));
            }
            s.reject(ev, "auth", &format!("RunMeta rejected: auth: from {}: matches no challenge we answered",
                                          hex(&pid)), 0, 0);
            continue;
        };
        let meta = decode_meta(&payload)?;
        let a = &meta["auth"];
        if a["nonce_plant"].as_str() != Some(&hex(&nq)) || a["nonce_controller"].as_str() != Some(&hex(&nr)) {
            s.reject(ev, "auth", &format!("RunMeta rejected: auth: from {}: its auth nonces are not the \
                                           session's", hex(&pid)), 0, 0);
            continue;
        }
        return Ok((pid, k_s, meta));
    }
}
