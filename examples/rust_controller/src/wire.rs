//! The messages of docs/protocol.md §3 (protocol 3): CDR little endian, the loop messages sealed
//! with the sender's id and a MAC, the others carrying them as zenoh attachment (auth.rs).

use crate::auth::{equal, h16, hex, Id, Key, ID_LEN, MAC_LEN};
use crate::MAX_AXES;

pub const VERSION: u16 = 3;
pub const ENCAP: [u8; 4] = [0, 1, 0, 0];
pub const TRAILER: usize = ID_LEN + MAC_LEN; // peer id, then the MAC of every byte before it

pub fn u16_at(b: &[u8], o: usize) -> u16 { u16::from_le_bytes(b[o..o + 2].try_into().unwrap()) }
pub fn u32_at(b: &[u8], o: usize) -> u32 { u32::from_le_bytes(b[o..o + 4].try_into().unwrap()) }
pub fn u64_at(b: &[u8], o: usize) -> u64 { u64::from_le_bytes(b[o..o + 8].try_into().unwrap()) }
pub fn f64_at(b: &[u8], o: usize) -> f64 { f64::from_le_bytes(b[o..o + 8].try_into().unwrap()) }

/// A rejected message: (reason code, text), docs/protocol.md §4.
pub type Reject = (&'static str, String);

pub fn check_header(b: &[u8], min: usize) -> Result<(), Reject> {
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

/// SensorSample -> (seq, step, sim_time_ns); displacements into `y`. It ends with the sender's
/// peer id and the MAC under `key` (K_s, topic plant/sensors): an id that is not `plant` is
/// rejected (`peer`), then a wrong MAC (`auth`), before the rest is read.
pub fn decode_sensor(b: &[u8], plant: &Id, key: &Key, y: &mut [f64]) -> Result<(u64, u64, i64), Reject> {
    check_header(b, 52)?;
    let (body, tag) = b.split_at(b.len() - MAC_LEN);
    let peer = &body[body.len() - ID_LEN..];
    if peer != plant {
        return Err(("peer", format!("sample seq {} from peer {}, not the paired plant {}",
                                    u64_at(b, 12), hex(peer), hex(plant))));
    }
    if !equal(&h16(key, &[body]), tag) {
        return Err(("auth", format!("sample from {} with a wrong MAC", hex(peer))));
    }
    let n = u32_at(b, 44) as usize;
    if n > MAX_AXES {
        return Err(("oversize", format!("{n} axes > {MAX_AXES}")));
    }
    if n == 0 || n != y.len() {
        return Err(("axes", format!("{n} axes, the run has {}", y.len())));
    }
    if b.len() != 52 + 8 * n + TRAILER {
        return Err(("length", format!("{} bytes != 52 + 8 x {n} + {TRAILER}", b.len())));
    }
    for (a, v) in y.iter_mut().enumerate() {
        *v = f64_at(b, 52 + 8 * a);
        if !v.is_finite() {
            return Err(("nonfinite", format!("displacement[{a}] = {v}")));
        }
    }
    Ok((u64_at(b, 12), u64_at(b, 20), u64_at(b, 28) as i64))
}

/// CurrentCommand into `out`: the currents, the sender's peer id `me`, the MAC under `key`
/// (K_s, topic controller/currents) of every byte before it (no attachment).
#[allow(clippy::too_many_arguments)]
pub fn encode_current(out: &mut Vec<u8>, seq: u64, step: u64, sim: i64, rx: i64, tx: i64, c: &[f64],
                      me: &Id, key: &Key) {
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
    let tag = h16(key, &[&out[..]]);
    out.extend_from_slice(&tag);
}

/// CDR string at `o` (u32 length incl. NUL, aligned to 4 from the body start) -> (text, next).
pub fn cdr_string(b: &[u8], mut o: usize) -> Option<(String, usize)> {
    o += (4 - (o - 4) % 4) % 4;
    let n = u32_at(b.get(..o + 4)?, o) as usize;
    let s = b.get(o + 4..o + 4 + n)?;
    if n == 0 || s[n - 1] != 0 {
        return None;
    }
    Some((String::from_utf8(s[..n - 1].to_vec()).ok()?, o + 4 + n))
}

pub fn put_string(out: &mut Vec<u8>, s: &str) {
    while (out.len() - 4) % 4 != 0 {
        out.push(0);
    }
    out.extend_from_slice(&(s.len() as u32 + 1).to_le_bytes());
    out.extend_from_slice(s.as_bytes());
    out.push(0);
}

/// Event payload (its attachment is made by the sender, auth::attachment).
pub fn encode_event(kind: u16, seq: u64, step: u64, sim: i64, wall: i64, source: &str, text: &str) -> Vec<u8> {
    let mut out = Vec::with_capacity(80 + text.len());
    out.extend_from_slice(&ENCAP);
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&kind.to_le_bytes());
    out.extend_from_slice(&[0; 4]);
    for v in [seq as i64, step as i64, sim, wall] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    put_string(&mut out, source);
    put_string(&mut out, text);
    out
}

/// An Event's fields.
pub struct Event { pub kind: u16, pub seq: u64, pub step: u64, pub source: String, pub text: String }

pub fn decode_event(b: &[u8]) -> Result<Event, Reject> {
    check_header(b, 44)?;
    let (source, o) = cdr_string(b, 44).ok_or(("string", "bad source string".to_string()))?;
    let (text, end) = cdr_string(b, o).ok_or(("string", "bad text string".to_string()))?;
    if end != b.len() {
        return Err(("length", format!("{} trailing bytes", b.len() - end)));
    }
    Ok(Event { kind: u16_at(b, 6), seq: u64_at(b, 12), step: u64_at(b, 20), source, text })
}

/// RunMeta -> its JSON object.
pub fn decode_meta(b: &[u8]) -> Result<serde_json::Value, String> {
    check_header(b, 44).map_err(|(r, t)| format!("RunMeta rejected: {r}: {t}"))?;
    let (text, _) = cdr_string(b, 44).ok_or("RunMeta rejected: string: bad string")?;
    let v: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| format!("RunMeta rejected: string: bad JSON: {e}"))?;
    if v.is_object() { Ok(v) } else { Err("RunMeta rejected: string: not a JSON object".into()) }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::auth::{h16, KEY_LEN};

    const PLANT: Id = [0xa5; ID_LEN];
    const KEY: Key = [0x3c; KEY_LEN];

    /// A SensorSample of `y` with version `ver`, `extra` bytes, the peer id `tail`, its MAC.
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
        let tag = h16(&KEY, &[&b[..]]);
        b.extend_from_slice(&tag);
        b
    }

    #[test]
    fn current_command_v3_layout() {
        let me: Id = core::array::from_fn(|i| i as u8 + 1);
        let mut out = Vec::new();
        for n in [1usize, 3, 6] {
            let c: Vec<f64> = (0..n).map(|a| 0.5 * (a + 1) as f64).collect();
            encode_current(&mut out, 7, 8, 9, 10, 11, &c, &me, &KEY);
            assert_eq!(out.len(), 92 + 8 * n);
            assert_eq!(out[..6], [0, 1, 0, 0, VERSION as u8, 0]);
            assert_eq!(out[60 + 8 * n..76 + 8 * n], me);
            assert_eq!(out[76 + 8 * n..], h16(&KEY, &[&out[..76 + 8 * n]]));
            assert_eq!((u64_at(&out, 12), u64_at(&out, 20), u32_at(&out, 52)), (7, 8, n as u32));
            assert_eq!(f64_at(&out, 60 + 8 * (n - 1)), c[n - 1]);
        }
    }

    #[test]
    fn sensor_sample_v3_checks() {
        let y3 = [0.001, 0.002, 0.003];
        let mut y = [0.0; 3];
        let ok = sample(3, 5, &y3, 0, &PLANT);
        assert_eq!(ok.len(), 52 + 24 + 32);
        assert_eq!(decode_sensor(&ok, &PLANT, &KEY, &mut y), Ok((5, 6, 7)));
        assert_eq!(y, y3);
        let reason = |b: &[u8]| decode_sensor(b, &PLANT, &KEY, &mut [0.0; 3]).unwrap_err();
        let (r, t) = reason(&sample(3, 5, &y3, 0, &[0x11; ID_LEN]));
        assert_eq!(r, "peer");
        assert!(t.contains(&"11".repeat(ID_LEN)) && t.contains(&hex(&PLANT)), "{t}");
        assert_eq!(reason(&decode_under(&ok, 60)).0, "auth"); // a flipped bit of the vector
        assert_eq!(decode_sensor(&ok, &PLANT, &[0x3d; KEY_LEN], &mut y).unwrap_err().0, "auth");
        assert_eq!(reason(&ok[..ok.len() - 16]).0, "peer"); // protocol-2 layout, no mac
        assert_eq!(reason(&sample(2, 5, &y3, 0, &PLANT)).0, "version");
        assert_eq!(reason(&sample(3, 5, &y3, 8, &PLANT)).0, "length");
        assert_eq!(reason(&sample(3, 5, &[0.0; 4], 0, &PLANT)).0, "axes");
        assert_eq!(reason(&sample(3, 5, &[0.0; 4], 0, &[0x11; ID_LEN])).0, "peer");
        assert_eq!(reason(&sample(3, 5, &[0.0, f64::NAN, 0.0], 0, &PLANT)).0, "nonfinite");
        assert_eq!(reason(&ok[..40]).0, "truncated");
    }

    fn decode_under(b: &[u8], flip: usize) -> Vec<u8> {
        let mut v = b.to_vec();
        v[flip] ^= 1;
        v
    }
}
