//! Adam with global-norm gradient clipping, written over a `VarStore`'s tensors.
//!
//! Why not `tch::nn::Optimizer`: its state (Adam's first and second moments)
//! lives inside libtorch's C++ optimizer object and tch offers no way to read or
//! write it, so a resumed run would restart Adam from zero moments and take
//! oversized steps. Here the moments are ordinary tensors keyed by variable name
//! and go into the checkpoint beside the weights (`optimizer.safetensors`).

use std::collections::BTreeMap;
use std::path::Path;

use tch::{Kind, Tensor, nn::VarStore};

/// Why a step was not taken: a loss or gradient norm that is NaN or
/// infinite, or libtorch's error from the backward pass (reported, never a
/// panic).
#[derive(Clone, Debug, PartialEq)]
pub enum StepRefused {
    Loss(f64),
    Gradient(f64),
    Backward(String),
}

impl std::fmt::Display for StepRefused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            StepRefused::Loss(v) => write!(f, "the loss is {v}"),
            StepRefused::Gradient(v) => write!(f, "the gradient norm is {v}"),
            StepRefused::Backward(e) => write!(f, "libtorch's backward pass failed: {e}"),
        }
    }
}

/// Adam's hyperparameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamConfig {
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// Global gradient-norm clip; `None` or non-positive disables clipping.
    pub grad_clip: Option<f64>,
}

/// Adam over every trainable variable of one `VarStore`, in name order.
#[derive(Debug)]
pub struct Adam {
    cfg: AdamConfig,
    /// (name, parameter, first moment, second moment), sorted by name.
    params: Vec<(String, Tensor, Tensor, Tensor)>,
    /// Steps taken (for bias correction).
    step: i64,
}

impl Adam {
    /// Zero moments for every trainable variable of `vs`.
    pub fn new(vs: &VarStore, cfg: AdamConfig) -> Self {
        let named: BTreeMap<String, Tensor> = vs.variables().into_iter().collect();
        let params = named
            .into_iter()
            .filter(|(_, t)| t.requires_grad())
            .map(|(name, t)| {
                let m = t.zeros_like();
                let v = t.zeros_like();
                (name, t, m, v)
            })
            .collect();
        Adam {
            cfg,
            params,
            step: 0,
        }
    }

    /// Bytes of the weights of `vs` plus Adam's two moments: what a
    /// checkpoint of them holds (the disk room checked before training).
    pub fn checkpoint_bytes(&self) -> u64 {
        3 * self
            .params
            .iter()
            .map(|(_, p, _, _)| (p.numel() * p.kind().elt_size_in_bytes()) as u64)
            .sum::<u64>()
    }

    /// Steps taken so far.
    pub fn step_count(&self) -> i64 {
        self.step
    }

    /// Changes the learning rate (schedules).
    pub fn set_lr(&mut self, lr: f64) {
        self.cfg.lr = lr;
    }

    /// Clears every parameter's gradient.
    pub fn zero_grad(&mut self) {
        for (_, p, _, _) in &mut self.params {
            let mut g = p.grad();
            if g.defined() {
                let _ = g.detach_().zero_();
            }
        }
    }

    /// Backpropagates `loss`, clips the global gradient norm and applies one
    /// Adam step. Returns the gradient norm before clipping (NaN, with no
    /// step taken, when the loss or a gradient is not finite: learners use
    /// [`Adam::try_backward_step`] to stop on that).
    pub fn backward_step(&mut self, loss: &Tensor) -> f64 {
        self.try_backward_step(loss).unwrap_or(f64::NAN)
    }

    /// [`Adam::backward_step`] that refuses to step when the loss or the
    /// gradient norm is NaN or infinite, or libtorch's backward pass fails:
    /// the parameters and moments stay as they were, and the error says why.
    pub fn try_backward_step(&mut self, loss: &Tensor) -> Result<f64, StepRefused> {
        self.try_backward(loss)?;
        self.try_step()
    }

    /// The first half of [`Adam::try_backward_step`]: backpropagates `loss`
    /// into cleared gradients, refusing a loss that is not finite and
    /// returning libtorch's error from the pass instead of panicking.
    pub fn try_backward(&mut self, loss: &Tensor) -> Result<(), StepRefused> {
        let loss_value = loss.double_value(&[]);
        if !loss_value.is_finite() {
            return Err(StepRefused::Loss(loss_value));
        }
        self.zero_grad();
        loss.f_backward()
            .map_err(|e| StepRefused::Backward(e.to_string()))
    }

    /// The second half: clips the gradients [`Adam::try_backward`] left and
    /// takes the Adam step; returns the norm before clipping, or refuses
    /// (clearing them) when it is not finite.
    pub fn try_step(&mut self) -> Result<f64, StepRefused> {
        let grads: Vec<Tensor> = self.params.iter().map(|(_, p, _, _)| p.grad()).collect();
        let defined: Vec<&Tensor> = grads.iter().filter(|g| g.defined()).collect();
        let norm = if defined.is_empty() {
            0.0
        } else {
            let sq: Vec<Tensor> = defined
                .iter()
                .map(|g| g.pow_tensor_scalar(2).sum(Kind::Float))
                .collect();
            Tensor::stack(&sq, 0)
                .sum(Kind::Float)
                .sqrt()
                .double_value(&[])
        };
        if !norm.is_finite() {
            self.zero_grad();
            return Err(StepRefused::Gradient(norm));
        }
        let scale = match self.cfg.grad_clip {
            Some(c) if c > 0.0 && norm > c => c / (norm + 1e-6),
            _ => 1.0,
        };
        self.step += 1;
        let (b1, b2) = (self.cfg.beta1, self.cfg.beta2);
        let bc1 = 1.0 - b1.powi(self.step as i32);
        let bc2 = 1.0 - b2.powi(self.step as i32);
        let step_size = self.cfg.lr / bc1;
        tch::no_grad(|| {
            for ((_, p, m, v), g) in self.params.iter_mut().zip(grads.iter()) {
                if !g.defined() {
                    continue;
                }
                let g = g * scale;
                // m <- b1 m + (1 - b1) g ;  v <- b2 v + (1 - b2) g^2
                let _ = m.g_mul_scalar_(b1).g_add_(&(&g * (1.0 - b1)));
                let _ = v.g_mul_scalar_(b2).g_add_(&(g.square() * (1.0 - b2)));
                // p <- p - lr / bc1 * m / (sqrt(v / bc2) + eps)
                let denom = (&*v / bc2).sqrt() + self.cfg.eps;
                let _ = p.g_sub_(&(&*m / denom * step_size));
            }
        });
        Ok(norm)
    }

    /// Writes the moments (`m/<name>`, `v/<name>`) and the step count
    /// (`step`) as safetensors.
    pub fn save(&self, path: &Path) -> Result<(), tch::TchError> {
        let mut named: Vec<(String, Tensor)> = Vec::with_capacity(2 * self.params.len() + 1);
        for (name, _, m, v) in &self.params {
            named.push((format!("m/{name}"), m.shallow_clone()));
            named.push((format!("v/{name}"), v.shallow_clone()));
        }
        named.push(("step".into(), Tensor::from_slice(&[self.step])));
        Tensor::write_safetensors(&named, path)
    }

    /// Reads moments written by [`Adam::save`]; every variable must be present
    /// with its shape and finite values (second moments non-negative), or the
    /// error names the first that is not.
    pub fn load(&mut self, path: &Path) -> Result<(), String> {
        let loaded = Tensor::read_safetensors(path).map_err(|e| e.to_string())?;
        let map: BTreeMap<String, Tensor> = loaded.into_iter().collect();
        let step = map
            .get("step")
            .ok_or_else(|| "no `step` entry".to_string())?;
        let step = if step.numel() == 1 {
            step.f_int64_value(&[0])
                .map_err(|e| format!("`step`: {e}"))?
        } else {
            return Err(format!("`step` holds {} values, expected 1", step.numel()));
        };
        if step < 0 {
            return Err(format!("`step` is {step}, expected 0 or more"));
        }
        tch::no_grad(|| {
            for (name, p, m, v) in &mut self.params {
                for (prefix, slot) in [("m", &mut *m), ("v", &mut *v)] {
                    let key = format!("{prefix}/{name}");
                    let t = map.get(&key).ok_or_else(|| format!("missing `{key}`"))?;
                    if t.size() != p.size() {
                        return Err(format!(
                            "`{key}` has shape {:?}, the model has {:?}",
                            t.size(),
                            p.size()
                        ));
                    }
                    let t = t.to_kind(tch::Kind::Float);
                    let finite = t.isfinite().all().int64_value(&[]) == 1;
                    let sign_ok = prefix == "m" || t.ge(0.0).all().int64_value(&[]) == 1;
                    if !(finite && sign_ok) {
                        return Err(format!(
                            "`{key}` holds NaN, infinite{} values",
                            if prefix == "v" { " or negative" } else { "" }
                        ));
                    }
                    slot.copy_(&t.to_device(p.device()));
                }
            }
            Ok(())
        })?;
        self.step = step;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, nn};

    /// The tests' Adam: lr 0.1, the usual betas and eps.
    fn config(grad_clip: Option<f64>) -> AdamConfig {
        AdamConfig {
            lr: 0.1,
            beta1: 0.9,
            beta2: 0.99,
            eps: 1e-8,
            grad_clip,
        }
    }

    #[test]
    fn adam_minimises_a_quadratic_and_clips() {
        let vs = nn::VarStore::new(Device::Cpu);
        let x = vs.root().var("x", &[3], nn::Init::Const(5.0));
        let cfg = config(Some(1.0));
        let mut opt = Adam::new(&vs, cfg);
        let first = opt.backward_step(&x.square().sum(Kind::Float));
        // Gradient 2x = 10 per entry: norm sqrt(300) before clipping.
        assert!((first - 300f64.sqrt()).abs() < 1e-3);
        for _ in 0..300 {
            opt.backward_step(&x.square().sum(Kind::Float));
        }
        assert!(x.abs().max().double_value(&[]) < 0.1);
    }

    #[test]
    fn a_non_finite_loss_or_gradient_takes_no_step() {
        let vs = nn::VarStore::new(Device::Cpu);
        let x = vs.root().var("x", &[2], nn::Init::Const(0.0));
        let cfg = config(Some(1.0));
        let mut opt = Adam::new(&vs, cfg);
        let e = opt
            .try_backward_step(&(x.sum(Kind::Float) * f64::NAN))
            .unwrap_err();
        assert!(matches!(e, StepRefused::Loss(v) if v.is_nan()), "{e}");
        // sqrt at 0: the loss is 0 but its gradient is infinite.
        let e = opt
            .try_backward_step(&x.sqrt().sum(Kind::Float))
            .unwrap_err();
        assert!(
            matches!(e, StepRefused::Gradient(v) if v.is_infinite()),
            "{e}"
        );
        assert_eq!(e.to_string(), "the gradient norm is inf");
        assert_eq!(opt.step_count(), 0, "no step was taken");
        assert_eq!(Vec::<f32>::try_from(&x).unwrap(), vec![0.0, 0.0]);
        assert!(
            opt.try_backward_step(&(&x - 1.0).square().sum(Kind::Float))
                .is_ok()
        );
    }

    #[test]
    fn a_backward_pass_that_libtorch_refuses_is_an_error_not_a_panic() {
        let vs = nn::VarStore::new(Device::Cpu);
        let x = vs.root().var("x", &[2], nn::Init::Const(0.0));
        let cfg = config(None);
        let mut opt = Adam::new(&vs, cfg);
        // A loss cut off from the parameters: libtorch finds no grad_fn.
        let e = opt
            .try_backward_step(&x.detach().sum(Kind::Float))
            .unwrap_err();
        assert!(
            matches!(&e, StepRefused::Backward(m) if m.contains("grad")),
            "{e}"
        );
        assert!(e.to_string().starts_with("libtorch's backward pass failed"));
        assert_eq!(opt.step_count(), 0, "no step was taken");
    }

    #[test]
    fn moments_round_trip() {
        let dir = std::env::temp_dir().join(format!("icrl-adam-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let vs = nn::VarStore::new(Device::Cpu);
        let x = vs.root().var("x", &[2], nn::Init::Const(1.0));
        let cfg = config(None);
        let mut a = Adam::new(&vs, cfg);
        a.backward_step(&x.square().sum(Kind::Float));
        a.save(&dir.join("o.safetensors")).unwrap();
        let mut b = Adam::new(&vs, cfg);
        b.load(&dir.join("o.safetensors")).unwrap();
        assert_eq!(b.step_count(), 1);
        assert_eq!(
            Vec::<f32>::try_from(&b.params[0].2).unwrap(),
            Vec::<f32>::try_from(&a.params[0].2).unwrap()
        );
        // Damaged moments or step are refused, naming the entry.
        let bad = dir.join("bad.safetensors");
        let m = Tensor::from_slice(&[0.1f32, f32::NAN]);
        let v = Tensor::from_slice(&[0.1f32, 0.2]);
        let step = Tensor::from_slice(&[3i64]);
        let write = |entries: &[(&str, &Tensor)]| {
            let named: Vec<(String, Tensor)> = entries
                .iter()
                .map(|(n, t)| (n.to_string(), t.shallow_clone()))
                .collect();
            Tensor::write_safetensors(&named, &bad).unwrap();
        };
        write(&[("m/x", &m), ("v/x", &v), ("step", &step)]);
        assert_eq!(
            b.load(&bad).unwrap_err(),
            "`m/x` holds NaN, infinite values"
        );
        write(&[("m/x", &v), ("v/x", &(-&v)), ("step", &step)]);
        assert!(
            b.load(&bad)
                .unwrap_err()
                .contains("`v/x` holds NaN, infinite or negative")
        );
        let empty = Tensor::from_slice::<i64>(&[]);
        write(&[("m/x", &v), ("v/x", &v), ("step", &empty)]);
        assert_eq!(
            b.load(&bad).unwrap_err(),
            "`step` holds 0 values, expected 1"
        );
        assert_eq!(b.step_count(), 1, "a refused file changes nothing");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
