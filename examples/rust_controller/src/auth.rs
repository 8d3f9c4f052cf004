//! Keys and MACs of a run (docs/protocol.md §5.3): keyed BLAKE2b, every key derived from the
//! run's 32-byte secret (a key file; without one the all-zero secret of an unauthenticated run).

use blake2::digest::consts::{U16, U32};
use blake2::digest::{KeyInit, Mac};
use blake2::Blake2bMac;

use crate::Res;

pub const ID_LEN: usize = 16;
pub const MAC_LEN: usize = 16;
pub const NONCE_LEN: usize = 16;
pub const KEY_LEN: usize = 32;
pub const ATTACH_LEN: usize = ID_LEN + MAC_LEN;

pub type Id = [u8; ID_LEN];
pub type Key = [u8; KEY_LEN];
pub type Tag = [u8; MAC_LEN];

/// H16(key, data): keyed BLAKE2b with a 16-byte digest.
pub fn h16(key: &[u8], parts: &[&[u8]]) -> Tag {
    let mut m = <Blake2bMac<U16> as KeyInit>::new_from_slice(key).expect("key <= 64 bytes");
    for p in parts {
        m.update(p);
    }
    m.finalize().into_bytes().into()
}

/// H32(key, data): keyed BLAKE2b with a 32-byte digest.
pub fn h32(key: &[u8], parts: &[&[u8]]) -> Key {
    let mut m = <Blake2bMac<U32> as KeyInit>::new_from_slice(key).expect("key <= 64 bytes");
    for p in parts {
        m.update(p);
    }
    m.finalize().into_bytes().into()
}

/// K_run: the pairing proofs and whatever is sent before pairing.
pub fn run_key(secret: &Key, run_id: &str) -> Key {
    h32(secret, &[b"ambhil/3/run\0", run_id.as_bytes()])
}

/// K_s: every message after pairing.
pub fn session_key(secret: &Key, run_id: &str, plant: &Id, controller: &Id, nonce_p: &[u8],
                   nonce_c: &[u8]) -> Key {
    h32(secret, &[b"ambhil/3/session\0", run_id.as_bytes(), b"\0", plant, controller, nonce_p, nonce_c])
}

/// K_topic under K_s (or K_run); topic = the key expression below `ambhil/<run>/`.
pub fn topic_key(base: &Key, topic: &str) -> Key {
    h32(base, &[b"ambhil/3/topic\0", topic.as_bytes()])
}

/// The answer to a challenge on `ambhil/<run>/pair/<role>/<responder id>`.
pub fn pair_proof(k_run: &Key, role: &str, responder: &Id, challenger: &[u8], nonce_q: &[u8],
                  nonce_r: &[u8]) -> Tag {
    h16(k_run, &[b"ambhil/3/pair\0", role.as_bytes(), b"\0", responder, challenger, nonce_q, nonce_r])
}

/// The zenoh attachment of every message but SensorSample / CurrentCommand: id, then its MAC.
pub fn attachment(key: &Key, me: &Id, payload: &[u8]) -> Vec<u8> {
    let mut a = me.to_vec();
    a.extend_from_slice(&h16(key, &[payload, me]));
    a
}

/// Constant-time comparison (a MAC check must not tell how many bytes matched).
pub fn equal(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// Does `att` carry `peer`'s id and a valid MAC of `payload` under `key`?
pub fn verify_attachment(key: &Key, payload: &[u8], att: Option<&[u8]>, peer: &Id) -> bool {
    match att {
        Some(a) if a.len() == ATTACH_LEN && a[..ID_LEN] == peer[..] => {
            equal(&h16(key, &[payload, peer]), &a[ID_LEN..])
        }
        _ => false,
    }
}

pub fn random<const N: usize>() -> Res<[u8; N]> {
    let mut b = [0u8; N];
    getrandom::getrandom(&mut b).map_err(|e| format!("no random bytes from the OS: {e}"))?;
    Ok(b)
}

/// The secret in a key file: 64 hex digits, the file readable by its owner only.
pub fn read_key_file(path: &str) -> Res<Key> {
    use std::os::unix::fs::PermissionsExt;
    let md = std::fs::metadata(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => format!("--key-file {path}: no such file (make one with \
                                                 `ambhil key {path}`)"),
        _ => format!("--key-file {path}: {e}"),
    })?;
    if !md.is_file() {
        return Err(format!("--key-file {path}: not a regular file"));
    }
    let mode = md.permissions().mode() & 0o7777;
    if mode & 0o077 != 0 {
        return Err(format!("--key-file {path}: mode {mode:04o} lets group or others read it; \
                            run `chmod 600 {path}`"));
    }
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("--key-file {path}: cannot read it ({e})"))?;
    let text = text.trim();
    let key: Option<Key> = unhex(text).and_then(|v| v.try_into().ok());
    let key = key.ok_or_else(|| format!("--key-file {path}: expected {} hex digits (a secret of \
                                         {KEY_LEN} bytes), found {} characters",
                                        2 * KEY_LEN, text.chars().count()))?;
    if key == [0; KEY_LEN] {
        return Err(format!("--key-file {path}: the all-zero secret is the unauthenticated one"));
    }
    Ok(key)
}

/// A listen endpoint only this host can reach (unauthenticated runs listen only there).
pub fn is_loopback(endpoint: &str) -> bool {
    let (proto, addr) = endpoint.split_once('/').unwrap_or((endpoint, ""));
    if proto.starts_with("unixsock") {
        return true;
    }
    let host = addr.rsplit_once(':').map(|(h, _)| h).unwrap_or(addr).trim_matches(|c| c == '[' || c == ']');
    host == "localhost" || host == "::1" || host.starts_with("127.")
}

pub fn hex(b: &[u8]) -> String { b.iter().map(|x| format!("{x:02x}")).collect() }

pub fn unhex(s: &str) -> Option<Vec<u8>> {
    if s.len() % 2 != 0 || !s.is_ascii() {
        return None;
    }
    (0..s.len()).step_by(2).map(|i| u8::from_str_radix(&s[i..i + 2], 16).ok()).collect()
}
