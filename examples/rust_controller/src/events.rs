//! The events: ours out (events/controller, attached, rate-limited) and the plant's in
//! (events/plant): what may be obeyed, what is rejected (docs/protocol.md §5.3, events).

use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use zenoh::Wait;

use crate::auth::{attachment, hex, verify_attachment, Id, Key, ATTACH_LEN, ID_LEN};
use crate::wall_ns;
use crate::wire::{decode_event, encode_event};

pub const EV_RUN_END: u16 = 2;
pub const EV_FAULT_INJECTED: u16 = 11;

pub struct Events<'a> {
    pub publ: zenoh::pubsub::Publisher<'a>,
    pub me: Id,
    pub key: Key,                    // topic events/controller under K_run, then under K_s
    pub seq: u64,
    pub window: (Instant, u32, u64), // (start of the second, sent in it, suppressed)
}

impl Events<'_> {
    /// Event from `controller`, at most 200 per second (the excess is counted in the next one).
    pub fn emit(&mut self, kind: u16, text: &str, step: u64, sim: i64, force: bool) {
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
        let out = encode_event(kind, self.seq, step, sim, wall_ns(), "controller", &text);
        self.seq += 1;
        let att = attachment(&self.key, &self.me, &out);
        let _ = self.publ.put(out).attachment(att).wait();
    }
}

/// The paired plant and the keys its events are checked with.
pub struct Paired { pub plant: Id, pub events: Key, pub events_run: Key }

/// What the liveliness tokens and the plant's events say; shared with the zenoh callbacks.
#[derive(Default)]
pub struct Peers {
    pub plant_starting: bool,
    pub plant_alive: bool,
    pub plant_seen: bool, // was ready once
    pub paired: Option<Paired>,
    pub early: Vec<(Vec<u8>, Option<Vec<u8>>)>, // events before pairing, judged once paired
    pub last_event_seq: i64,                    // of the plant's accepted events (-1: none)
    pub run_end: Option<String>,                // RUN_END text from the paired plant
    pub restarts: Vec<u64>,                     // steps of controller_restart faults to come
    pub rejects: Vec<(&'static str, String)>,   // events rejected, for the main loop to report
}

pub type Shared = Arc<(Mutex<Peers>, Condvar)>;

/// An event on events/plant: obeyed (RUN_END, FAULT_INJECTED controller_restart) only with the
/// paired plant's id, a MAC under K_s and a seq beyond the last accepted one; else rejected.
pub fn judge_event(p: &mut Peers, payload: &[u8], att: Option<&[u8]>) {
    let Some(s) = &p.paired else {
        if p.early.len() < 1024 {
            p.early.push((payload.to_vec(), att.map(|a| a.to_vec())));
        }
        return;
    };
    let session = if verify_attachment(&s.events, payload, att, &s.plant) {
        true
    } else if verify_attachment(&s.events_run, payload, att, &s.plant) {
        false // sent before pairing (start-up): recorded by others, never obeyed
    } else {
        let who = att.filter(|a| a.len() == ATTACH_LEN).map(|a| hex(&a[..ID_LEN])).unwrap_or("?".into());
        p.rejects.push(("auth", format!("event rejected: auth: from {who}: not the paired plant's, or a wrong MAC")));
        return;
    };
    let e = match decode_event(payload) {
        Ok(e) => e,
        Err((r, t)) => return p.rejects.push((r, format!("event rejected: {r}: {t}"))),
    };
    if e.source != "plant" && e.source != "replay" {
        return p.rejects.push(("auth", format!("event rejected: auth: source {:?} on events/plant", e.source)));
    }
    if !session {
        return;
    }
    if (e.seq as i64) <= p.last_event_seq {
        let t = format!("event rejected: sequence: seq {}, last {}", e.seq, p.last_event_seq);
        return p.rejects.push(("sequence", t));
    }
    p.last_event_seq = e.seq as i64;
    if e.kind == EV_RUN_END {
        p.run_end = Some(e.text);
    } else if e.kind == EV_FAULT_INJECTED && e.source == "plant" {
        let v: serde_json::Value = serde_json::from_str(&e.text).unwrap_or_default();
        if v["kind"] == "controller_restart" && v["phase"] == "start" {
            p.restarts.push(e.step);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::auth::KEY_LEN;
    use crate::EV_INFO;

    const PLANT: Id = [0xa5; ID_LEN];

    #[test]
    fn events_obeyed_only_from_the_paired_plant_in_sequence() {
        let ks: Key = [7; KEY_LEN];
        let mut p = Peers { last_event_seq: -1, ..Default::default() };
        let end = encode_event(EV_RUN_END, 3, 0, 0, 0, "plant", "{}");
        judge_event(&mut p, &end, None); // before pairing: kept for later
        assert_eq!(p.early.len(), 1);
        p.paired = Some(Paired { plant: PLANT, events: ks, events_run: [8; KEY_LEN] });
        judge_event(&mut p, &end, Some(&attachment(&[9; KEY_LEN], &PLANT, &end))); // wrong key
        judge_event(&mut p, &end, Some(&attachment(&ks, &[1; ID_LEN], &end)));     // wrong id
        assert_eq!(p.rejects.iter().map(|r| r.0).collect::<Vec<_>>(), ["auth", "auth"]);
        judge_event(&mut p, &end, Some(&attachment(&[8; KEY_LEN], &PLANT, &end))); // K_run: not obeyed
        assert!(p.run_end.is_none() && p.rejects.len() == 2);
        let info = encode_event(EV_INFO, 5, 0, 0, 0, "plant", "x");
        judge_event(&mut p, &info, Some(&attachment(&ks, &PLANT, &info)));
        judge_event(&mut p, &end, Some(&attachment(&ks, &PLANT, &end)));          // seq 3 <= 5: replay
        assert!(p.run_end.is_none() && p.rejects.last().unwrap().0 == "sequence");
        let end = encode_event(EV_RUN_END, 6, 0, 0, 0, "plant", "{\"reason\": \"completed\"}");
        judge_event(&mut p, &end, Some(&attachment(&ks, &PLANT, &end)));
        assert_eq!(p.run_end.as_deref(), Some("{\"reason\": \"completed\"}"));
    }
}
