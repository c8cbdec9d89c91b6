//! Checks every learner shares, so nothing runs on settings or values that
//! would silently go wrong:
//! - [`Range`] and [`check_numbers`]: every numeric setting in its allowed
//!   range, the range named in the error (`lr = NaN: must be a finite number
//!   in (0, inf)`);
//! - [`check_counts`]: counts that must be at least 1;
//! - [`regular_file`]: an input that is not a regular file (a FIFO would
//!   block its reader), refused before it is opened;
//! - [`non_finite_variable`]: the first weight of a `VarStore` holding NaN or
//!   infinity (training refuses to go on, evaluation refuses to load);
//! - [`MemoryEstimate`]: what a configuration will allocate (parameters, Adam
//!   moments, replay, one batch's activations), checked against the memory
//!   `/proc/meminfo` reports before anything is allocated.

use std::fmt;

use tch::nn::VarStore;

/// An interval of allowed values, shown as it reads in the error:
/// `(0, inf)`, `[0, 1)`, `[0, 1]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Range {
    pub low: f64,
    pub low_open: bool,
    pub high: f64,
    pub high_open: bool,
}

impl Range {
    /// (0, inf)
    pub const POSITIVE: Range = Range::new(0.0, true, f64::INFINITY, true);
    /// [0, inf)
    pub const NON_NEGATIVE: Range = Range::new(0.0, false, f64::INFINITY, true);
    /// [0, 1]
    pub const UNIT: Range = Range::new(0.0, false, 1.0, false);
    /// [0, 1)
    pub const UNIT_OPEN_HIGH: Range = Range::new(0.0, false, 1.0, true);
    /// (0, 1]
    pub const UNIT_OPEN_LOW: Range = Range::new(0.0, true, 1.0, false);
    /// (-inf, inf): any finite number.
    pub const FINITE: Range = Range::new(f64::NEG_INFINITY, true, f64::INFINITY, true);

    pub const fn new(low: f64, low_open: bool, high: f64, high_open: bool) -> Self {
        Range {
            low,
            low_open,
            high,
            high_open,
        }
    }

    /// True for a finite value inside the interval.
    pub fn contains(&self, v: f64) -> bool {
        v.is_finite()
            && (if self.low_open {
                v > self.low
            } else {
                v >= self.low
            })
            && (if self.high_open {
                v < self.high
            } else {
                v <= self.high
            })
    }
}

impl fmt::Display for Range {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let num = |x: f64| {
            if x == f64::INFINITY {
                "inf".to_string()
            } else if x == f64::NEG_INFINITY {
                "-inf".to_string()
            } else {
                short_number(x)
            }
        };
        write!(
            f,
            "{}{}, {}{}",
            if self.low_open { '(' } else { '[' },
            num(self.low),
            num(self.high),
            if self.high_open { ')' } else { ']' }
        )
    }
}

/// A number as a message shows it: as Rust writes it where that is short,
/// in exponent form far from 1 (`1e-300`, not 300 zeros: the hand rerun of
/// trial 3 met a message of 300 digits).
pub fn short_number(x: f64) -> String {
    if x == 0.0 || !x.is_finite() || (1e-4..1e16).contains(&x.abs()) {
        format!("{x}")
    } else {
        format!("{x:e}")
    }
}

/// Checks `(name, value, range)` in order; the error names the first value
/// outside its range and the range.
pub fn check_numbers(items: &[(&str, f64, Range)]) -> Result<(), String> {
    for &(name, value, range) in items {
        if !range.contains(value) {
            return Err(format!(
                "{name} = {}: must be a finite number in {range}",
                short_number(value)
            ));
        }
    }
    Ok(())
}

/// Checks a `torch_threads` setting: 0 (libtorch's default) to 1024.
pub fn check_torch_threads(n: i32) -> Result<(), String> {
    if (0..=1024).contains(&n) {
        Ok(())
    } else {
        Err(format!(
            "torch_threads = {n}: must be in [0, 1024] (0 keeps libtorch's default)"
        ))
    }
}

/// Sets libtorch's intra-op threads for this OS thread from a thread-count
/// setting (`torch_threads`, `learner_threads`): 0 keeps libtorch's default,
/// and a count above this machine's cores is held to the cores, with a
/// warning once, since threads past the cores only wait on each other (1024
/// on 2 busy cores stalled a 2-update run for minutes). Presets ask for 1
/// or 2, so they run as written.
pub fn set_torch_threads(name: &str, setting: i32) {
    if setting <= 0 {
        return;
    }
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let threads = setting.min(i32::try_from(cores).unwrap_or(i32::MAX));
    if threads < setting {
        static WARNED: std::sync::Once = std::sync::Once::new();
        WARNED.call_once(|| {
            eprintln!(
                "warning: {name} = {setting} is more than this machine's {cores} cores: libtorch \
                 uses {threads}"
            );
        });
    }
    tch::set_num_threads(threads);
}

/// Checks that every count is at least 1; the error names the first that is not.
pub fn check_counts(items: &[(&str, i128)]) -> Result<(), String> {
    for &(name, value) in items {
        if value < 1 {
            return Err(format!("{name} = {value}: must be at least 1"));
        }
    }
    Ok(())
}

/// Refuses an input that exists but is not a regular file, before anything
/// opens it: opening a FIFO blocks until a writer comes, where no stop
/// signal ends the wait, and a device, socket or folder holds nothing to
/// read. The error says what it is (`it is a FIFO, not a regular file`);
/// a path that does not exist passes (its reader names that).
pub fn regular_file(path: &std::path::Path) -> Result<(), String> {
    match std::fs::metadata(path) {
        Ok(meta) if !meta.is_file() => Err(format!(
            "it is {}, not a regular file",
            safety_envs::output::kind(&meta.file_type())
        )),
        _ => Ok(()),
    }
}

/// `path` as a message shows it: whole up to 120 characters; a longer one
/// (a user may pass thousands) by its first and last 48 characters and its
/// length, `dddd…/eeee (4036 characters)`.
pub fn short_path(path: &std::path::Path) -> String {
    let text = path.display().to_string();
    let chars: Vec<char> = text.chars().collect();
    if chars.len() <= 120 {
        return text;
    }
    let head: String = chars[..48].iter().collect();
    let tail: String = chars[chars.len() - 48..].iter().collect();
    format!("{head}…{tail} ({} characters)", chars.len())
}

/// The name of the first variable of `vs` (in name order) holding NaN or
/// infinity, with how many of its values are not finite.
pub fn non_finite_variable(vs: &VarStore) -> Option<(String, i64)> {
    let mut vars = vs.variables().into_iter().collect::<Vec<_>>();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    tch::no_grad(|| {
        for (name, t) in vars {
            let bad = t
                .isfinite()
                .logical_not()
                .sum(tch::Kind::Int64)
                .int64_value(&[]);
            if bad > 0 {
                return Some((name, bad));
            }
        }
        None
    })
}

/// What the memory estimate compares against: `MemAvailable` (and
/// `MemTotal`) from `/proc/meminfo`, in bytes. `None` where the file is
/// missing (not Linux): then no check is made.
pub fn machine_memory() -> Option<(u64, u64)> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let field = |key: &str| -> Option<u64> {
        let line = text.lines().find(|l| l.starts_with(key))?;
        let kb: u64 = line
            .trim_start_matches(key)
            .trim()
            .trim_end_matches("kB")
            .trim()
            .parse()
            .ok()?;
        Some(kb * 1024)
    };
    let total = field("MemTotal:")?;
    Some((field("MemAvailable:").unwrap_or(total), total))
}

pub use safety_envs::output::human_bytes;

/// Memory a configuration needs, by part, in bytes (f64: a silly setting
/// must not overflow the estimate itself).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MemoryEstimate {
    pub parts: Vec<(String, f64)>,
    /// Settings that drive the estimate, named in the error as what to lower.
    pub levers: String,
}

impl MemoryEstimate {
    /// Adds a part.
    pub fn add(&mut self, name: &str, bytes: f64) {
        self.parts.push((name.into(), bytes));
    }

    /// Total bytes.
    pub fn total(&self) -> f64 {
        self.parts.iter().map(|p| p.1).sum()
    }

    /// Refuses an estimate above the machine's available memory, with the
    /// estimate by part and the machine's memory in the message.
    pub fn check(&self) -> Result<(), String> {
        self.check_against(machine_memory())
    }

    /// [`MemoryEstimate::check`] against given (available, total) bytes.
    pub fn check_against(&self, memory: Option<(u64, u64)>) -> Result<(), String> {
        let total = self.total();
        let Some((available, machine_total)) = memory else {
            return Ok(());
        };
        if total.is_finite() && total <= available as f64 {
            return Ok(());
        }
        let parts = self
            .parts
            .iter()
            .map(|(n, b)| format!("{n} {}", human_bytes(*b)))
            .collect::<Vec<_>>()
            .join(", ");
        Err(format!(
            "this configuration needs about {} ({parts}), but the machine has {} available \
             ({} total, from /proc/meminfo); lower {}",
            human_bytes(total),
            human_bytes(available as f64),
            human_bytes(machine_total as f64),
            self.levers
        ))
    }
}

/// Parameters of the shared transformer (see `model.rs`): per block an
/// attention (qkv and output projections) and an MLP, two layer norms; a
/// final norm; a position table of `max_len` rows (learned, or the fixed
/// sinusoids, which take the same memory without being trained).
pub fn transformer_parameters(cfg: &crate::model::Config) -> f64 {
    let d = cfg.d_model as f64;
    let ff = cfg.d_ff as f64;
    let block = (d * 3.0 * d + 3.0 * d) + (d * d + d) + (d * ff + ff) + (ff * d + d) + 4.0 * d;
    cfg.n_layers as f64 * block + 2.0 * d + cfg.max_len as f64 * d
}

/// Bytes of float32 activations the transformer keeps for backward over one
/// batch of `batch` sequences: per block the residual stream, norms, q/k/v
/// and the MLP hidden layer. Causal attention goes through libtorch's fused
/// kernel, which keeps O(T) per head; with attention dropout it may take
/// the math path instead, which keeps the (B, H, T, T) weights: counted then.
pub fn transformer_activation_bytes(cfg: &crate::model::Config, batch: f64) -> f64 {
    let (d, ff, t, h) = (
        cfg.d_model as f64,
        cfg.d_ff as f64,
        cfg.max_len as f64,
        cfg.n_heads as f64,
    );
    let weights = if cfg.attn_dropout > 0.0 {
        2.0 * batch * h * t * t
    } else {
        2.0 * batch * h * t
    };
    let per_block = batch * t * (10.0 * d + 2.0 * ff) + weights;
    4.0 * (cfg.n_layers as f64 * per_block + 2.0 * batch * t * d)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// More threads than cores run as many as the cores; a count within
    /// them, as asked; 0 leaves libtorch's count alone.
    #[test]
    fn thread_settings_are_held_to_the_cores() {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get()) as i32;
        std::thread::spawn(move || {
            set_torch_threads("torch_threads", 1024.max(cores + 1));
            assert_eq!(tch::get_num_threads(), cores);
            set_torch_threads("torch_threads", 1);
            assert_eq!(tch::get_num_threads(), 1);
            set_torch_threads("torch_threads", 0);
            assert_eq!(tch::get_num_threads(), 1);
        })
        .join()
        .unwrap();
    }

    #[test]
    fn ranges_refuse_nan_infinity_and_values_outside_naming_the_range() {
        assert!(Range::POSITIVE.contains(1e-3));
        assert!(!Range::POSITIVE.contains(0.0));
        assert!(!Range::POSITIVE.contains(f64::NAN));
        assert!(!Range::NON_NEGATIVE.contains(f64::INFINITY));
        assert!(Range::UNIT_OPEN_HIGH.contains(0.0) && !Range::UNIT_OPEN_HIGH.contains(1.0));
        let e = check_numbers(&[
            ("beta1", 0.9, Range::UNIT_OPEN_HIGH),
            ("lr", f64::NAN, Range::POSITIVE),
        ])
        .unwrap_err();
        assert_eq!(e, "lr = NaN: must be a finite number in (0, inf)");
        let e = check_numbers(&[("lr", -1.0, Range::POSITIVE)]).unwrap_err();
        assert!(e.contains("lr = -1") && e.contains("(0, inf)"), "{e}");
        let e = check_counts(&[("batch_size", 4), ("updates_per_round", 0)]).unwrap_err();
        assert_eq!(e, "updates_per_round = 0: must be at least 1");
        // Far from 1, in exponent form (300 digits before the hand rerun).
        let scale = Range::new(0.0, true, 1e6, false);
        let e = check_numbers(&[("reward_scale", 1e300, scale)]).unwrap_err();
        assert_eq!(
            e,
            "reward_scale = 1e300: must be a finite number in (0, 1000000]"
        );
        let tiny = Range::new(f64::from(f32::MIN_POSITIVE), false, 1.0, false);
        let e = check_numbers(&[("adam_eps", 1e-300, tiny)]).unwrap_err();
        assert_eq!(
            e,
            "adam_eps = 1e-300: must be a finite number in [1.1754943508222875e-38, 1]"
        );
    }

    #[test]
    fn memory_estimate_names_parts_and_the_machine() {
        let mut m = MemoryEstimate {
            levers: "batch_size".into(),
            ..Default::default()
        };
        m.add("parameters", 4e6);
        m.add("one batch's activations", 4.8e12);
        let e = m
            .check_against(Some((8_000_000_000, 16_000_000_000)))
            .unwrap_err();
        assert!(
            e.contains("4.8 TB") && e.contains("8.0 GB available"),
            "{e}"
        );
        assert!(
            e.contains("16.0 GB total") && e.contains("lower batch_size"),
            "{e}"
        );
        m.parts.pop();
        m.check_against(Some((8_000_000_000, 16_000_000_000)))
            .unwrap();
        // A non-finite estimate (overflowing settings) is refused too.
        m.add("replay", f64::INFINITY);
        assert!(m.check_against(Some((1, 1))).is_err());
        let (avail, total) = machine_memory().expect("/proc/meminfo on Linux");
        assert!(avail > 0 && avail <= total);
    }

    #[test]
    fn non_finite_weights_are_named() {
        let vs = VarStore::new(tch::Device::Cpu);
        let _a = vs.root().zeros("a", &[3]);
        let b = vs.root().zeros("b", &[2]);
        assert_eq!(non_finite_variable(&vs), None);
        tch::no_grad(|| {
            let _ = b.narrow(0, 1, 1).fill_(f64::NAN);
        });
        assert_eq!(non_finite_variable(&vs), Some(("b".into(), 1)));
    }
}
