//! The one causal transformer shared by every learner (EPPO, supervised
//! distillation): nanoGPT-style, pre-norm, over input embeddings. The caller owns
//! its token encoder and its heads; this module maps (B, T, D) to (B, T, D).
//!
//! Small parts first (attention, MLP, block), then the configuration and the
//! top-level [`Transformer`]. Variable-path names equal field names: they are the
//! checkpoint format (`h/0/attn/c_attn/weight`, ...).
//!
//! Incremental decoding: a [`KvCache`] (owned by the caller, one per batch of
//! trajectories, with an explicit [`KvCache::reset`]) holds each layer's keys and
//! values; [`Transformer::forward_step`] continues from the cached positions and
//! equals the full forward to float tolerance (tested below).

use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor, nn, nn::Module};
use thiserror::Error;

/// A configuration the transformer cannot be built with, or a call it cannot serve.
#[derive(Debug, Error)]
pub enum ModelError {
    #[error("model config: {0}")]
    Config(String),
    #[error(
        "sequence of {total} steps exceeds the model's max_len {max_len} (cache held {cached}, input {new})"
    )]
    TooLong {
        total: i64,
        max_len: i64,
        cached: i64,
        new: i64,
    },
    #[error("input shape {got:?}: expected (B, T, {d_model})")]
    Shape { got: Vec<i64>, d_model: i64 },
    #[error("KV cache holds batch {cached}, input has batch {got}: reset the cache first")]
    CacheBatch { cached: i64, got: i64 },
}

/// The deepest transformer a config may ask for: 8 times the deepest preset
/// (trial 3's edge fuzz: 100000 layers of width 16 passed the memory
/// estimate, then held 16.8 GB, twice the estimate in per-tensor overhead,
/// and had not finished its first update when SIGTERM came at 60 s; 500
/// layers took 66 s for two updates).
pub const MOST_LAYERS: i64 = 64;

/// How positions are encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Positions {
    /// A learned embedding table of `max_len` rows.
    Learned,
    /// Fixed sinusoids (Vaswani et al.), AMAGO's default.
    Sinusoidal,
}

/// Shape of the transformer (Table 1 / Table 2 of the paper).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Width of every token embedding (Table 1 "Embedding Dim").
    pub d_model: i64,
    /// Attention heads; must divide `d_model`.
    pub n_heads: i64,
    /// Transformer blocks.
    pub n_layers: i64,
    /// Hidden width of each block's MLP (Table 1 "Hidden Dim").
    pub d_ff: i64,
    /// Longest sequence the model accepts (Table 1 "Seq Len").
    pub max_len: i64,
    /// Dropout on the attention weights.
    pub attn_dropout: f64,
    /// Dropout on each residual branch's output.
    pub resid_dropout: f64,
    /// Dropout on the input embeddings (after adding positions).
    pub embd_dropout: f64,
    /// Position encoding.
    pub positions: Positions,
}

impl Config {
    /// Checks every constraint, naming the values that break it.
    pub fn validate(&self) -> Result<(), ModelError> {
        let positive = [
            ("d_model", self.d_model),
            ("n_heads", self.n_heads),
            ("n_layers", self.n_layers),
            ("d_ff", self.d_ff),
            ("max_len", self.max_len),
        ];
        for (name, value) in positive {
            if value <= 0 {
                return Err(ModelError::Config(format!(
                    "{name} = {value} must be positive"
                )));
            }
        }
        if self.n_layers > MOST_LAYERS {
            return Err(ModelError::Config(format!(
                "n_layers = {}: at most {MOST_LAYERS} (every agent step runs each layer's \
                 kernels one after another: far deeper, a run takes minutes per update and \
                 stops late when asked)",
                self.n_layers
            )));
        }
        if self.d_model % self.n_heads != 0 {
            return Err(ModelError::Config(format!(
                "d_model = {} is not divisible by n_heads = {}",
                self.d_model, self.n_heads
            )));
        }
        if self.positions == Positions::Sinusoidal && self.d_model % 2 != 0 {
            return Err(ModelError::Config(format!(
                "sinusoidal positions need an even d_model, got {}",
                self.d_model
            )));
        }
        let dropouts = [
            ("attn_dropout", self.attn_dropout),
            ("resid_dropout", self.resid_dropout),
            ("embd_dropout", self.embd_dropout),
        ];
        for (name, p) in dropouts {
            if !(0.0..1.0).contains(&p) {
                return Err(ModelError::Config(format!(
                    "{name} = {p} must lie in [0, 1)"
                )));
            }
        }
        Ok(())
    }

    fn head_dim(&self) -> i64 {
        self.d_model / self.n_heads
    }
}

/// Keys and values of one layer for the positions seen so far.
#[derive(Debug, Default)]
struct LayerKv {
    /// Key and value buffers, (B, H, max_len, Dh) each, allocated at the first
    /// step; positions `0..len` are filled. New positions are written in place,
    /// so a step copies only its own keys and values (no regrowth by `cat`).
    buf: Option<(Tensor, Tensor)>,
    /// Positions filled.
    len: i64,
}

/// Cached keys and values of every layer: lets acting cost O(T) per step instead
/// of recomputing the whole context. One cache serves one batch of B
/// trajectories advanced in lockstep; call [`KvCache::reset`] at trajectory
/// boundaries.
#[derive(Debug)]
pub struct KvCache {
    layers: Vec<LayerKv>,
    len: i64,
}

impl KvCache {
    /// An empty cache for a model of `n_layers` blocks.
    pub fn new(n_layers: i64) -> Self {
        let layers = (0..n_layers).map(|_| LayerKv::default()).collect();
        KvCache { layers, len: 0 }
    }

    /// Forgets every cached position (start of new trajectories).
    pub fn reset(&mut self) {
        for layer in &mut self.layers {
            layer.buf = None;
            layer.len = 0;
        }
        self.len = 0;
    }

    /// Positions cached so far.
    pub fn len(&self) -> i64 {
        self.len
    }

    /// True when nothing is cached.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Batch size of the cached trajectories, if any.
    fn batch(&self) -> Option<i64> {
        self.layers
            .first()
            .and_then(|l| l.buf.as_ref())
            .map(|(k, _)| k.size()[0])
    }
}

/// Multi-head causal self-attention.
#[derive(Debug)]
struct CausalSelfAttention {
    /// Query, key and value projections in one matrix: D -> 3D.
    c_attn: nn::Linear,
    /// Output projection: D -> D.
    c_proj: nn::Linear,
    n_heads: i64,
    head_dim: i64,
    max_len: i64,
    attn_dropout: f64,
    resid_dropout: f64,
}

impl CausalSelfAttention {
    fn new(p: nn::Path, cfg: &Config) -> Self {
        let d = cfg.d_model;
        CausalSelfAttention {
            c_attn: nn::linear(&p / "c_attn", d, 3 * d, Default::default()),
            c_proj: nn::linear(&p / "c_proj", d, d, Default::default()),
            n_heads: cfg.n_heads,
            head_dim: cfg.head_dim(),
            max_len: cfg.max_len,
            attn_dropout: cfg.attn_dropout,
            resid_dropout: cfg.resid_dropout,
        }
    }

    /// `x`: (B, T, D). With `cache`, the T new positions follow the cached ones
    /// and the cache is extended.
    fn forward(&self, x: &Tensor, train: bool, cache: Option<&mut LayerKv>) -> Tensor {
        let (b, t, d) = x.size3().expect("attention input is (B, T, D)");
        let qkv = self.c_attn.forward(x); // (B, T, 3D)
        let parts = qkv.split(d, 2);
        // (B, T, D) -> (B, T, H, Dh) -> (B, H, T, Dh)
        let heads = |z: &Tensor| z.view([b, t, self.n_heads, self.head_dim]).transpose(1, 2);
        let q = heads(&parts[0]);
        let mut k = heads(&parts[1]);
        let mut v = heads(&parts[2]);
        let mut past_len = 0;
        if let Some(cache) = cache {
            past_len = cache.len;
            let (kb, vb) = cache.buf.get_or_insert_with(|| {
                let shape = [b, self.n_heads, self.max_len, self.head_dim]; // (B, H, max_len, Dh)
                let opts = (k.kind(), k.device());
                (Tensor::zeros(shape, opts), Tensor::zeros(shape, opts))
            });
            // Write the new positions in place, then attend over the filled prefix.
            kb.narrow(2, past_len, t).copy_(&k);
            vb.narrow(2, past_len, t).copy_(&v);
            k = kb.narrow(2, 0, past_len + t); // (B, H, T_past + T, Dh), a view
            v = vb.narrow(2, 0, past_len + t); // (B, H, T_past + T, Dh), a view
            cache.len = past_len + t;
        }
        let dropout = if train { self.attn_dropout } else { 0.0 };
        let y = if past_len == 0 {
            // No past: the plain causal mask.
            Tensor::scaled_dot_product_attention(
                &q,
                &k,
                &v,
                None::<Tensor>,
                dropout,
                true,
                None,
                false,
            )
        } else if t == 1 {
            // One new position sees every cached one: no mask needed.
            Tensor::scaled_dot_product_attention(
                &q,
                &k,
                &v,
                None::<Tensor>,
                dropout,
                false,
                None,
                false,
            )
        } else {
            // Several new positions after a past: new row i sees keys 0..=past_len + i.
            // (T, T_past + T), true = may attend; aligned bottom-right.
            let mask = Tensor::ones([t, past_len + t], (Kind::Bool, x.device())).tril(past_len);
            Tensor::scaled_dot_product_attention(
                &q,
                &k,
                &v,
                Some(mask),
                dropout,
                false,
                None,
                false,
            )
        }; // (B, H, T, Dh)
        let y = y.transpose(1, 2).contiguous().view([b, t, d]); // (B, H, T, Dh) -> (B, T, D)
        self.c_proj.forward(&y).dropout(self.resid_dropout, train)
    }
}

/// The position-wise feed-forward network: D -> d_ff -> D with GELU.
#[derive(Debug)]
struct Mlp {
    c_fc: nn::Linear,
    c_proj: nn::Linear,
    resid_dropout: f64,
}

impl Mlp {
    fn new(p: nn::Path, cfg: &Config) -> Self {
        Mlp {
            c_fc: nn::linear(&p / "c_fc", cfg.d_model, cfg.d_ff, Default::default()),
            c_proj: nn::linear(&p / "c_proj", cfg.d_ff, cfg.d_model, Default::default()),
            resid_dropout: cfg.resid_dropout,
        }
    }

    fn forward(&self, x: &Tensor, train: bool) -> Tensor {
        self.c_proj
            .forward(&self.c_fc.forward(x).gelu("none"))
            .dropout(self.resid_dropout, train)
    }
}

/// One pre-norm block: x + attn(ln_1(x)), then x + mlp(ln_2(x)).
#[derive(Debug)]
struct Block {
    ln_1: nn::LayerNorm,
    attn: CausalSelfAttention,
    ln_2: nn::LayerNorm,
    mlp: Mlp,
}

impl Block {
    fn new(p: nn::Path, cfg: &Config) -> Self {
        let d = cfg.d_model;
        Block {
            ln_1: nn::layer_norm(&p / "ln_1", vec![d], Default::default()),
            attn: CausalSelfAttention::new(&p / "attn", cfg),
            ln_2: nn::layer_norm(&p / "ln_2", vec![d], Default::default()),
            mlp: Mlp::new(&p / "mlp", cfg),
        }
    }

    fn forward(&self, x: &Tensor, train: bool, cache: Option<&mut LayerKv>) -> Tensor {
        let x = x + self.attn.forward(&self.ln_1.forward(x), train, cache);
        &x + self.mlp.forward(&self.ln_2.forward(&x), train)
    }
}

/// Sinusoidal position table, (max_len, D).
fn sinusoids(max_len: i64, d: i64, device: tch::Device) -> Tensor {
    let pos = Tensor::arange(max_len, (Kind::Float, device)).unsqueeze(1); // (L, 1)
    let i = Tensor::arange_start_step(0, d, 2, (Kind::Float, device)); // (D/2,)
    let inv_freq = (i * (-(10_000f64.ln()) / d as f64)).exp(); // (D/2,)
    let angles = pos * inv_freq.unsqueeze(0); // (L, D/2)
    // Interleave sin and cos: (L, D/2, 2) -> (L, D)
    Tensor::stack(&[angles.sin(), angles.cos()], 2).view([max_len, d])
}

/// The causal transformer over a sequence of input embeddings.
#[derive(Debug)]
pub struct Transformer {
    cfg: Config,
    /// Learned position table, or None for sinusoids.
    wpe: Option<nn::Embedding>,
    /// Fixed sinusoid table (not a variable: not in checkpoints).
    sinusoid: Option<Tensor>,
    h: Vec<Block>,
    ln_f: nn::LayerNorm,
}

impl Transformer {
    /// Builds the transformer under `p`, after checking `cfg`.
    pub fn new(p: nn::Path, cfg: &Config) -> Result<Self, ModelError> {
        cfg.validate()?;
        let (wpe, sinusoid) = match cfg.positions {
            Positions::Learned => (
                Some(nn::embedding(
                    &p / "wpe",
                    cfg.max_len,
                    cfg.d_model,
                    Default::default(),
                )),
                None,
            ),
            Positions::Sinusoidal => (None, Some(sinusoids(cfg.max_len, cfg.d_model, p.device()))),
        };
        let h = (0..cfg.n_layers)
            .map(|i| Block::new(&p / "h" / i, cfg))
            .collect();
        let ln_f = nn::layer_norm(&p / "ln_f", vec![cfg.d_model], Default::default());
        Ok(Transformer {
            cfg: cfg.clone(),
            wpe,
            sinusoid,
            h,
            ln_f,
        })
    }

    /// The configuration it was built with.
    pub fn config(&self) -> &Config {
        &self.cfg
    }

    /// A fresh cache sized for this model.
    pub fn new_cache(&self) -> KvCache {
        KvCache::new(self.cfg.n_layers)
    }

    /// Position encodings for positions `start..start + t`, (T, D).
    fn positions(&self, start: i64, t: i64, device: tch::Device) -> Tensor {
        match (&self.wpe, &self.sinusoid) {
            (Some(wpe), _) => wpe.forward(&Tensor::arange_start(
                start,
                start + t,
                (Kind::Int64, device),
            )),
            (None, Some(table)) => table.narrow(0, start, t),
            (None, None) => unreachable!("one position encoding is always built"),
        }
    }

    fn check_input(&self, x: &Tensor, cached: i64) -> Result<(i64, i64), ModelError> {
        let size = x.size();
        if size.len() != 3 || size[2] != self.cfg.d_model {
            return Err(ModelError::Shape {
                got: size,
                d_model: self.cfg.d_model,
            });
        }
        if cached + size[1] > self.cfg.max_len {
            return Err(ModelError::TooLong {
                total: cached + size[1],
                max_len: self.cfg.max_len,
                cached,
                new: size[1],
            });
        }
        Ok((size[0], size[1]))
    }

    /// Full causal forward: `x` (B, T, D) of input embeddings at positions
    /// 0..T -> (B, T, D). `train` enables dropout.
    pub fn forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor, ModelError> {
        let (_, t) = self.check_input(x, 0)?;
        let pos = self.positions(0, t, x.device()).unsqueeze(0); // (1, T, D)
        let mut h = (x + pos).dropout(self.cfg.embd_dropout, train);
        for block in &self.h {
            h = block.forward(&h, train, None);
        }
        Ok(self.ln_f.forward(&h))
    }

    /// Incremental forward for acting (no dropout): `x` (B, T_new, D) holds the
    /// next T_new steps (usually 1) after the `cache.len()` cached ones; returns
    /// (B, T_new, D) and extends the cache.
    pub fn forward_step(&self, x: &Tensor, cache: &mut KvCache) -> Result<Tensor, ModelError> {
        let start = cache.len;
        let (b, t) = self.check_input(x, start)?;
        if let Some(cached) = cache.batch()
            && cached != b
        {
            return Err(ModelError::CacheBatch { cached, got: b });
        }
        if cache.layers.len() as i64 != self.cfg.n_layers {
            *cache = self.new_cache();
        }
        let pos = self.positions(start, t, x.device()).unsqueeze(0); // (1, T_new, D)
        let mut h = x + pos;
        for (block, layer) in self.h.iter().zip(cache.layers.iter_mut()) {
            h = block.forward(&h, false, Some(layer));
        }
        cache.len += t;
        Ok(self.ln_f.forward(&h))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, nn::VarStore};

    fn cfg(positions: Positions) -> Config {
        Config {
            d_model: 16,
            n_heads: 4,
            n_layers: 2,
            d_ff: 32,
            max_len: 40,
            attn_dropout: 0.1,
            resid_dropout: 0.1,
            embd_dropout: 0.1,
            positions,
        }
    }

    fn max_abs_diff(a: &Tensor, b: &Tensor) -> f64 {
        (a - b).abs().max().double_value(&[])
    }

    #[test]
    fn cached_decoding_equals_full_forward() {
        for positions in [Positions::Learned, Positions::Sinusoidal] {
            let vs = VarStore::new(Device::Cpu);
            let model =
                crate::torch_rng::seeded(0, || Transformer::new(vs.root(), &cfg(positions)))
                    .unwrap();
            for len in [1, 2, 7, 40] {
                let x = crate::torch_rng::drawing(|| {
                    Tensor::randn([3, len, 16], (Kind::Float, Device::Cpu))
                });
                let full = tch::no_grad(|| model.forward_t(&x, false).unwrap());
                let mut cache = model.new_cache();
                let steps: Vec<Tensor> = (0..len)
                    .map(|i| {
                        tch::no_grad(|| model.forward_step(&x.narrow(1, i, 1), &mut cache).unwrap())
                    })
                    .collect();
                let stepped = Tensor::cat(&steps, 1);
                let diff = max_abs_diff(&full, &stepped);
                assert!(diff < 1e-5, "{positions:?} len {len}: diff {diff}");
                assert_eq!(cache.len(), len);
                // A chunk of several steps after a cached prefix also matches.
                if len > 3 {
                    cache.reset();
                    let a = tch::no_grad(|| {
                        model.forward_step(&x.narrow(1, 0, 2), &mut cache).unwrap()
                    });
                    let b = tch::no_grad(|| {
                        model
                            .forward_step(&x.narrow(1, 2, len - 2), &mut cache)
                            .unwrap()
                    });
                    let diff = max_abs_diff(&full, &Tensor::cat(&[a, b], 1));
                    assert!(diff < 1e-5, "chunked len {len}: diff {diff}");
                }
            }
        }
    }

    #[test]
    fn future_steps_do_not_change_past_outputs() {
        let vs = VarStore::new(Device::Cpu);
        let (model, x) = crate::torch_rng::seeded(1, || {
            let model = Transformer::new(vs.root(), &cfg(Positions::Sinusoidal)).unwrap();
            (
                model,
                Tensor::randn([2, 10, 16], (Kind::Float, Device::Cpu)),
            )
        });
        let y = x.copy();
        let _ = y.narrow(1, 6, 4).fill_(3.0);
        let a = tch::no_grad(|| model.forward_t(&x, false).unwrap());
        let b = tch::no_grad(|| model.forward_t(&y, false).unwrap());
        assert!(max_abs_diff(&a.narrow(1, 0, 6), &b.narrow(1, 0, 6)) < 1e-6);
        assert!(max_abs_diff(&a.narrow(1, 6, 4), &b.narrow(1, 6, 4)) > 1e-3);
    }

    #[test]
    fn bad_configs_name_their_values() {
        let mut c = cfg(Positions::Learned);
        c.n_heads = 3;
        let err = c.validate().unwrap_err().to_string();
        assert!(
            err.contains("d_model = 16") && err.contains("n_heads = 3"),
            "{err}"
        );
        let mut c = cfg(Positions::Learned);
        c.attn_dropout = 1.5;
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("attn_dropout = 1.5")
        );
        let vs = VarStore::new(Device::Cpu);
        let model =
            crate::torch_rng::drawing(|| Transformer::new(vs.root(), &cfg(Positions::Learned)))
                .unwrap();
        let too_long = Tensor::zeros([1, 41, 16], (Kind::Float, Device::Cpu));
        let err = model.forward_t(&too_long, false).unwrap_err().to_string();
        assert!(err.contains("41") && err.contains("40"), "{err}");
        let mut cache = model.new_cache();
        let one = Tensor::zeros([2, 1, 16], (Kind::Float, Device::Cpu));
        let _ = model.forward_step(&one, &mut cache).unwrap();
        let other_batch = Tensor::zeros([3, 1, 16], (Kind::Float, Device::Cpu));
        assert!(matches!(
            model.forward_step(&other_batch, &mut cache),
            Err(ModelError::CacheBatch { cached: 2, got: 3 })
        ));
    }
}
