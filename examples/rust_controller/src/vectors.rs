//! `rust_controller --selftest-vectors FILE`: computes the outputs of the shared test vectors
//! (tests/fixtures/auth_vectors.json, its `inputs`) with this example's own functions and prints
//! them as one JSON object; tests/test_auth_vectors.py compares them with the file's `outputs`.

use serde_json::{json, Map, Value};

use crate::auth::{attachment, hex, pair_proof, run_key, session_key, topic_key, unhex, verify_attachment,
                  Id, Key};
use crate::wire::{decode_sensor, encode_current, encode_event};
use crate::Res;

fn bytes<const N: usize>(v: &Value, k: &str) -> Res<[u8; N]> {
    v.get(k).and_then(|x| x.as_str()).and_then(unhex).and_then(|b| b.try_into().ok())
        .ok_or_else(|| format!("vectors: `{k}` is not {N} bytes of hex"))
}

fn int(v: &Value, k: &str) -> Res<i64> {
    v.get(k).and_then(|x| x.as_i64()).ok_or_else(|| format!("vectors: `{k}` is not an integer"))
}

fn floats(v: &Value, k: &str) -> Res<Vec<f64>> {
    v.get(k).and_then(|x| x.as_array()).map(|a| a.iter().filter_map(|x| x.as_f64()).collect())
        .ok_or_else(|| format!("vectors: `{k}` is not a list of numbers"))
}

fn text<'a>(v: &'a Value, k: &str) -> Res<&'a str> {
    v.get(k).and_then(|x| x.as_str()).ok_or_else(|| format!("vectors: `{k}` is not a string"))
}

pub fn selftest(path: &str) -> Res<String> {
    let file: Value = serde_json::from_str(&std::fs::read_to_string(path).map_err(|e| format!("{path}: {e}"))?)
        .map_err(|e| format!("{path}: {e}"))?;
    let inp = file.get("inputs").ok_or("vectors: no `inputs`")?;
    let out = file.get("outputs").ok_or("vectors: no `outputs`")?;
    let secret: Key = bytes(inp, "secret")?;
    let run = text(inp, "run_id")?;
    let (pid, cid): (Id, Id) = (bytes(inp, "plant_id")?, bytes(inp, "controller_id")?);
    let (n_p, n_c): ([u8; 16], [u8; 16]) = (bytes(inp, "nonce_plant")?, bytes(inp, "nonce_controller")?);
    let k_run = run_key(&secret, run);
    let k_s = session_key(&secret, run, &pid, &cid, &n_p, &n_c);
    let topics: Vec<&str> = inp.get("topics").and_then(|t| t.as_array())
        .map(|a| a.iter().filter_map(|x| x.as_str()).collect()).unwrap_or_default();
    let keys = |base: &Key| -> Map<String, Value> {
        topics.iter().map(|t| (t.to_string(), json!(hex(&topic_key(base, t))))).collect()
    };
    let c = inp.get("current_command").ok_or("vectors: no current_command")?;
    let mut cur = Vec::new();
    encode_current(&mut cur, int(c, "seq")? as u64, int(c, "step")? as u64, int(c, "sim_time_ns")?,
                   int(c, "recv_wall_ns")?, int(c, "publish_wall_ns")?, &floats(c, "current")?, &cid,
                   &topic_key(&k_s, "controller/currents"));
    let e = inp.get("event").ok_or("vectors: no event")?;
    let ev = encode_event(int(e, "kind")? as u16, int(e, "seq")? as u64, int(e, "step")? as u64,
                          int(e, "sim_time_ns")?, int(e, "wall_ns")?, text(e, "source")?, text(e, "text")?);
    // what it receives: the sealed sample (and the same with one bit flipped), the RunMeta
    let sample = unhex(text(out, "sensor_sample")?).ok_or("vectors: sensor_sample")?;
    let k_sensors = topic_key(&k_s, "plant/sensors");
    let n = floats(inp.get("sensor_sample").ok_or("vectors: no sensor_sample")?, "displacement")?.len();
    let mut y = vec![0.0; n];
    let (seq, step, sim) = decode_sensor(&sample, &pid, &k_sensors, &mut y)
        .map_err(|(r, t)| format!("vectors: the sealed sample is rejected: {r}: {t}"))?;
    let mut decoded = vec![json!(seq), json!(step), json!(sim)];
    decoded.extend(y.iter().map(|v| json!(v)));
    let mut flipped = vec![];
    for at in [sample.len() - 20, 60] {           // a byte of the peer id, a byte of the vector
        let mut bad = sample.clone();
        bad[at] ^= 1;
        flipped.push(json!(decode_sensor(&bad, &pid, &k_sensors, &mut y).err().map(|(r, _)| r)));
    }
    let meta = unhex(text(out, "run_meta_payload")?).ok_or("vectors: run_meta_payload")?;
    let meta_att = unhex(text(out, "run_meta_attachment")?).ok_or("vectors: run_meta_attachment")?;
    let res = json!({
        "k_run": hex(&k_run),
        "k_run_unauthenticated": hex(&run_key(&[0; 32], run)),
        "k_session": hex(&k_s),
        "topic_keys": keys(&k_s),
        "run_topic_keys": keys(&k_run),
        "proof_controller": hex(&pair_proof(&k_run, "controller", &cid, &pid, &n_p, &n_c)),
        "proof_plant": hex(&pair_proof(&k_run, "plant", &pid, &cid, &n_c, &n_p)),
        "current_command": hex(&cur),
        "event_payload": hex(&ev),
        "event_attachment": hex(&attachment(&topic_key(&k_s, "events/controller"), &cid, &ev)),
        "event_attachment_run": hex(&attachment(&topic_key(&k_run, "events/controller"), &cid, &ev)),
        "sensor_sample_decoded": decoded,
        "sensor_sample_flipped_rejected": flipped,
        "run_meta_verifies": verify_attachment(&topic_key(&k_s, "meta"), &meta, Some(&meta_att), &pid),
    });
    Ok(res.to_string())
}
