//! The controller's law (docs/protocol.md §5.2): the four discrete blocks of RunMeta
//! `controller`, in the exact operation order of the built-in controller (bit for bit).

use crate::{Res, MAX_AXES};

/// One first-order discrete block: x' = a x + b u, y = c x + d u.
#[derive(Clone, Copy, Debug)]
pub struct Block { a: f64, b: f64, c: f64, d: f64 }

/// The discrete per-axis law of RunMeta `controller` (docs/protocol.md §5.2).
pub struct Law {
    sensor: Block, integral: Block, derivative: Block, amplifier: Block,
    kp: f64, ilim: f64, ulim: f64, anti_windup: bool, nd: usize, i_op: Vec<f64>,
}

/// Controller state: per axis [sensor, integrator, derivative, amplifier], the delay line.
pub struct State { x: Vec<[f64; 4]>, line: Vec<f64>, k: usize }

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
    pub fn from_meta(meta: &serde_json::Value) -> Res<Law> {
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

    pub fn n_axes(&self) -> usize { self.i_op.len() }

    /// Equilibrium at zero displacement with output i_op (docs/protocol.md §5.2, "start").
    pub fn initial_state(&self) -> State {
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
    pub fn step(&self, st: &mut State, y: &[f64], cur: &mut [f64]) {
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
