//! The command line (the `--selftest-vectors FILE` form is taken by main before this).

use crate::Res;

pub struct Args {
    pub run_id: String,
    pub connect: Vec<String>,
    pub listen: Vec<String>,
    pub key_file: Option<String>,
    pub insecure: bool,
    pub start_timeout: f64,
    pub sample_timeout: f64,
}

const USAGE: &str = "rust_controller --run-id ID --connect ENDPOINT [--listen ENDPOINT] [--key-file FILE] \
                     [--insecure] [--start-timeout S] [--sample-timeout S]\n\
                     rust_controller --selftest-vectors FILE";

pub fn parse_args() -> Res<Args> {
    let mut a = Args { run_id: String::new(), connect: vec![], listen: vec![], key_file: None, insecure: false,
                       start_timeout: 30.0, sample_timeout: 300.0 };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut val = || it.next().ok_or_else(|| format!("{flag}: missing value"));
        match flag.as_str() {
            "--run-id" => a.run_id = val()?,
            "--connect" => a.connect.push(val()?),
            "--listen" => a.listen.push(val()?),
            "--key-file" => a.key_file = Some(val()?),
            "--insecure" => a.insecure = true,
            "--start-timeout" | "--sample-timeout" => {
                let v = val()?;
                let s: f64 = v.parse().ok().filter(|s: &f64| *s > 0.0)
                    .ok_or_else(|| format!("{flag}: expected a positive number of s, got {v:?}"))?;
                if flag == "--start-timeout" { a.start_timeout = s } else { a.sample_timeout = s }
            }
            "-h" | "--help" => {
                println!("{USAGE}");
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
    if a.key_file.is_none() {
        a.key_file = std::env::var("AMBHIL_KEY_FILE").ok().filter(|s| !s.is_empty());
    }
    if a.listen.is_empty() {
        a.listen.push("tcp/127.0.0.1:0".into()); // so gossip can link the recorder to us
    }
    Ok(a)
}
