//! AD's tests: labels, windows, the loss, training, resuming and the frozen agent.

use super::*;
use crate::agent::{Actions, AgentError, Conditioning, InContextAgent, StepInput};
use crate::checkpoint::read_manifest;
use crate::data::dataset::{DatasetConfig, Source, generate};
use safety_envs::EnvName;

fn tiny_cfg() -> AdConfig {
    let mut cfg = AdConfig::preset("darkroom-quick").unwrap();
    cfg.model.n_layers = 2;
    cfg.model.d_model = 32;
    cfg.model.n_heads = 4;
    cfg.model.d_ff = 64;
    cfg.model.max_len = 40;
    cfg.model.attn_dropout = 0.0;
    cfg.model.resid_dropout = 0.0;
    cfg.model.embd_dropout = 0.0;
    cfg.batch_size = 16;
    cfg.updates = 120;
    cfg.learning_rate = 3e-3;
    cfg.log_every = 20;
    cfg.checkpoint_every = 60;
    cfg.val_fraction = 0.0;
    cfg
}

/// An empty temporary folder named after `what` and this process.
fn fresh_dir(what: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("icrl-ad-{what}-{}", std::process::id()));
    let _ = fs::remove_dir_all(&dir);
    dir
}

/// A fresh training run of `cfg` on `data` into `dir`.
fn request<'a>(cfg: &'a AdConfig, data: &'a HistoryFile, dir: &'a Path) -> TrainRequest<'a> {
    TrainRequest {
        cfg,
        data,
        dataset_path: Path::new("tiny.h5"),
        run_dir: dir,
        resume: None,
    }
}

fn tiny_data() -> HistoryFile {
    let mut d = DatasetConfig::paper(EnvName::DarkRoom, 2, 11);
    d.source = Source::NoisyOptimal;
    d.steps = 1500;
    d.cost_limits = vec![0.0];
    generate(&d, &|_| {}).unwrap().file
}

/// A history of `lens.len()` episodes of the given lengths: observation
/// (episode, step), action = episode % 5, reward 1 and cost 1 at each
/// episode's last step, next observation (episode, 100 + step).
fn history_of(lens: &[usize]) -> History {
    let task = safety_envs::Task {
        grid_size: 9,
        goal: safety_envs::Cell { row: 0, col: 0 },
        obstacles: vec![],
    };
    let mut h = History::new(task, 0.0);
    for (e, &len) in lens.iter().enumerate() {
        for t in 0..len {
            let last = t + 1 == len;
            h.push(
                &[e as f32, t as f32],
                &[(e % 5) as f32],
                if last { 1.0 } else { 0.0 },
                if last { 1.0 } else { 0.0 },
                &[e as f32, 100.0 + t as f32],
                last,
                false,
            );
        }
    }
    h
}

#[test]
fn windows_join_whole_episodes_stride_apart() {
    let h = history_of(&[3, 4, 2, 5, 3, 4, 2, 3, 5, 4, 3, 2, 4, 3, 5, 2, 3, 4]);
    let mut spec = spec_for(&tiny_data(), Path::new("x.h5"));
    (spec.obs_mean, spec.obs_std) = (vec![0.0; 2], vec![1.0; 2]);
    let mut cfg = tiny_cfg();
    cfg.episode_stride_max = 3;
    let set = TokenSet::new(&spec, &cfg, &[&h]);
    let hs = &set.histories[0];
    let episode_of = |t: usize| hs.episodes.iter().position(|r| r.contains(&t)).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut strides_seen = [false; 4];
    for _ in 0..200 {
        let steps = set.window_steps(hs, 12, &mut rng);
        assert_eq!(steps.len(), 12);
        // Episodes in the window: whole after the first, one stride apart.
        let eps: Vec<usize> = steps.iter().map(|&t| episode_of(t)).collect();
        let mut distinct = eps.clone();
        distinct.dedup();
        let stride = distinct.get(1).map(|e| e - distinct[0]);
        for w in distinct.windows(2) {
            assert_eq!(Some(w[1] - w[0]), stride, "{eps:?}");
        }
        for (i, &t) in steps.iter().enumerate().skip(1) {
            if eps[i] != eps[i - 1] {
                assert_eq!(t, hs.episodes[eps[i]].start, "{steps:?}");
            } else {
                assert_eq!(t, steps[i - 1] + 1);
            }
        }
        if let Some(s) = stride {
            assert!((1..=3).contains(&s));
            strides_seen[s] = true;
        }
        // Each token says what the previous step in the window received.
        let mut x = Vec::new();
        set.push_window(hs, &steps, &mut x);
        let d = spec.token_dim();
        for (i, &t) in steps.iter().enumerate() {
            let tok = &x[i * d..(i + 1) * d];
            assert_eq!(
                &tok[..2],
                &[eps[i] as f32, (t - hs.episodes[eps[i]].start) as f32]
            );
            if i == 0 {
                assert!(tok[2..11].iter().all(|&v| v == 0.0), "{tok:?}");
                continue;
            }
            let p = steps[i - 1];
            let (pe, pt) = (eps[i - 1], p - hs.episodes[eps[i - 1]].start);
            // Arrived observation, the previous action (one-hot), reward, cost.
            assert_eq!(&tok[2..4], &[pe as f32, 100.0 + pt as f32]);
            let mut onehot = [0.0f32; 5];
            onehot[pe % 5] = 1.0;
            assert_eq!(&tok[4..9], &onehot);
            let ended = eps[i] != pe;
            assert_eq!(tok[9], if ended { 1.0 } else { 0.0 });
            assert_eq!(tok[10], if ended { 1.0 } else { 0.0 });
            assert_eq!(tok[d - 1], if ended { 1.0 } else { 0.0 });
            // CTG: the cost still to come in the episode, scaled; never negative.
            assert_eq!(tok[d - 2], 1.0 / cfg.ctg_scale);
        }
    }
    assert_eq!(strides_seen, [false, true, true, true]);
    // Stride 1 is the contiguous history.
    cfg.episode_stride_max = 1;
    let set = TokenSet::new(&spec, &cfg, &[&h]);
    for _ in 0..50 {
        let steps = set.window_steps(&set.histories[0], 12, &mut rng);
        assert!(steps.windows(2).all(|w| w[1] == w[0] + 1), "{steps:?}");
    }
}

#[test]
fn the_ablation_trains_on_a_fraction_of_the_tasks() {
    let mut d = DatasetConfig::paper(EnvName::DarkRoom, 8, 11);
    d.source = Source::NoisyOptimal;
    d.steps = 300;
    d.cost_limits = vec![0.0, 5.0];
    let data = generate(&d, &|_| {}).unwrap().file;
    let mut cfg = tiny_cfg();
    (cfg.updates, cfg.val_fraction, cfg.train_fraction) = (2, 0.25, 0.5);
    let dir = fresh_dir("frac");
    let s = train(&request(&cfg, &data, &dir), &mut |_| {}, &mut |_| {}).unwrap();
    // 8 tasks: 2 held out; half of the other 6 trained on; 2 limits each.
    assert_eq!((s.train_histories, s.val_histories), (6, 4));
    let _ = fs::remove_dir_all(&dir);
}

#[test]
fn presets_parse_and_match_table_2() {
    let t2 = AdConfig::preset("darkroom-table2").unwrap();
    assert_eq!(
        (
            t2.model.d_model,
            t2.model.d_ff,
            t2.model.n_layers,
            t2.model.n_heads,
            t2.model.max_len
        ),
        (64, 512, 8, 8, 100)
    );
    assert_eq!((t2.batch_size, t2.updates), (512, 300_000));
    assert_eq!(
        (
            t2.model.attn_dropout,
            t2.model.resid_dropout,
            t2.model.embd_dropout
        ),
        (0.5, 0.1, 0.3)
    );
    for env in ["darkroom", "point", "car"] {
        for p in ["table2", "quick"] {
            AdConfig::preset(&format!("{env}-{p}")).unwrap();
        }
    }
    let e = AdConfig::preset("darkroom-table1").unwrap_err().to_string();
    assert!(e.contains("ad-darkroom-quick"), "{e}");
}

#[test]
fn to_go_labels_count_what_is_still_to_come() {
    let data = tiny_data();
    let h = &data.histories[0];
    let (rtg, ctg) = to_go(h, CtgLabel::Hindsight);
    let eps = h.episodes();
    let e = &eps[0];
    let ret: f32 = h.rewards[e.clone()].iter().sum();
    let cost: f32 = h.costs[e.clone()].iter().sum();
    assert_eq!(rtg[e.start], ret);
    assert_eq!(ctg[e.start], cost);
    assert_eq!(rtg[e.end - 1], h.rewards[e.end - 1]);
    assert_eq!(ctg[e.end - 1], h.costs[e.end - 1]);
    // Budget labels: the limit left before each step, never below 0.
    let mut h = history_of(&[4, 3]);
    h.costs = vec![1.0, 1.0, 0.0, 1.0, 1.0, 0.0, 0.0];
    h.cost_limit = 1.5;
    let (_, ctg) = to_go(&h, CtgLabel::Budget);
    assert_eq!(ctg, vec![1.5, 0.5, 0.0, 0.0, 1.5, 0.5, 0.5]);
}

#[test]
fn supervised_loss_falls_and_the_agent_acts_from_a_checkpoint() {
    let data = tiny_data();
    let cfg = tiny_cfg();
    let dir = fresh_dir("test");
    let req = request(&cfg, &data, &dir);
    let mut logs = Vec::new();
    let s = train(&req, &mut |m| logs.push(m.clone()), &mut |_| {}).unwrap();
    assert_eq!(s.updates, 120);
    let (first, last) = (logs[0].train_loss, logs[logs.len() - 1].train_loss);
    // Uniform over 5 actions is ln 5 = 1.61.
    assert!(last < 0.8 * first && last < 1.3, "loss {first} -> {last}");

    // The agent loads, acts past its context (sliding) and the cache agrees
    // with a full forward on the same tokens.
    let (mut agent, info) = AdAgent::load(&dir).unwrap();
    assert_eq!(info.updates_done, 120);
    agent
        .reset(&[Conditioning::Targets { rtg: 1.0, ctg: 0.0 }; 2])
        .unwrap();
    let mut outs = Vec::new();
    for t in 0..100 {
        let input = StepInput {
            obs: &[4.0, 4.0, 4.0, 5.0],
            arrived_obs: &[4.0, 4.0, 4.0, 5.0],
            prev_action: &[0.0; 10],
            reward: &[0.0, 0.0],
            cost: &[0.0, 1.0],
            episode_start: &[t % 30 == 0, t % 30 == 0],
        };
        outs.push(agent.act(&input, true).unwrap());
    }
    assert!(matches!(&outs[99], Actions::Discrete(v) if v.len() == 2 && v[0] < 5));
    assert!(agent.cache.len() <= cfg.model.max_len);
    // CTG fell by the cost received since the last episode start (t = 90)
    // and stopped at 0, the lowest label training ever showed.
    assert_eq!(agent.ctg[1], 0.0);
    assert_eq!(agent.ctg[0], 0.0);
    let last = agent.window.as_ref().unwrap().select(1, -1); // (B, token_dim)
    let ctg_part: Vec<f32> = last
        .select(1, agent.spec.token_dim() as i64 - 2)
        .try_into()
        .unwrap();
    assert_eq!(ctg_part, vec![0.0, 0.0]);
    assert!(matches!(
        agent.reset(&[Conditioning::Budget { ctg: 1.0 }]),
        Err(AgentError::Input(_))
    ));

    // Checkpoints are atomic step folders with checksummed manifests.
    let step_60 = dir.join("checkpoints/step_60");
    let m = read_manifest(&step_60).unwrap();
    assert_eq!((m.method.as_str(), m.updates), ("ad", 60));
    assert_eq!(m.sha256.len(), 3, "model, adam, state: {:?}", m.sha256);
    assert!(dir.join("checkpoints/step_120").is_dir());
    // One step folder loads too, for evaluation of an earlier checkpoint.
    let (_, info) = AdAgent::load(&step_60).unwrap();
    assert_eq!((info.updates_done, info.dir.clone()), (60, step_60.clone()));
    let loaded = crate::eval::load::load_checkpoint(&step_60, EnvName::DarkRoom).unwrap();
    assert_eq!(loaded.checkpoint, Some(step_60.clone()));

    // Resuming from step 60 redoes 61..120: the metrics lines logged after
    // the checkpoint are dropped, so no update is counted twice.
    let resume = TrainRequest {
        resume: Some(&step_60),
        ..req.clone()
    };
    let s = train(&resume, &mut |_| {}, &mut |_| {}).unwrap();
    assert_eq!((s.resumed_from, s.updates), (60, 120));
    let updates: Vec<usize> = fs::read_to_string(dir.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<AdMetrics>(l).unwrap().update)
        .collect();
    assert_eq!(updates, vec![20, 40, 60, 80, 100, 120]);
    // A longer run continues from the latest checkpoint ...
    let mut more = cfg.clone();
    more.updates = 140;
    let step_120 = dir.join("checkpoints/step_120");
    let longer = TrainRequest {
        cfg: &more,
        resume: Some(&step_120),
        ..req.clone()
    };
    let s = train(&longer, &mut |_| {}, &mut |_| {}).unwrap();
    assert_eq!((s.resumed_from, s.updates), (120, 140));
    // ... and any other change is refused, naming the field.
    let mut other_lr = more.clone();
    other_lr.learning_rate = 1e-3;
    let other = TrainRequest {
        cfg: &other_lr,
        ..longer
    };
    let e = train(&other, &mut |_| {}, &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("learning_rate: 0.003 -> 0.001"), "{e}");
    // Other data (here: every observation shifted) is refused by name.
    let mut shifted = data.clone();
    for h in &mut shifted.histories {
        h.observations.iter_mut().for_each(|o| *o += 1.0);
    }
    let other_data = TrainRequest {
        data: &shifted,
        ..longer.clone()
    };
    let e = train(&other_data, &mut |_| {}, &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("is not the one the run was trained on"), "{e}");
    // Fewer updates than done: refused with the fix.
    let step_140 = dir.join("checkpoints/step_140");
    let shorter = TrainRequest {
        resume: Some(&step_140),
        ..req.clone()
    };
    let e = train(&shorter, &mut |_| {}, &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("--set updates=140"), "{e}");
    // A run whose tokens lack the arrived observation is refused by name.
    let spec_path = dir.join("spec.json");
    let spec_text = fs::read_to_string(&spec_path).unwrap();
    let mut old: serde_json::Value = serde_json::from_str(&spec_text).unwrap();
    old.as_object_mut().unwrap().remove("token");
    fs::write(&spec_path, old.to_string()).unwrap();
    let e = AdAgent::load(&dir).err().unwrap().to_string();
    assert!(e.contains("arrived") && e.contains("retrain"), "{e}");
    fs::write(&spec_path, spec_text).unwrap();
    // Altered weights (same size) are refused on resume and on load.
    let model = step_140.join("model.safetensors");
    let mut bytes = fs::read(&model).unwrap();
    let n = bytes.len();
    for b in &mut bytes[n - 64..] {
        *b = b.wrapping_add(1);
    }
    fs::write(&model, bytes).unwrap();
    let e = AdAgent::load(&dir).err().unwrap().to_string();
    assert!(
        e.contains("model.safetensors") && e.contains("SHA-256"),
        "{e}"
    );
    let _ = fs::remove_dir_all(&dir);
}

#[test]
fn kv_cache_step_equals_full_forward() {
    let data = tiny_data();
    let cfg = tiny_cfg();
    let spec = spec_for(&data, Path::new("x"));
    let vs = nn::VarStore::new(Device::Cpu);
    let model = AdModel::new(&vs.root(), &spec, &cfg).unwrap();
    let set = TokenSet::new(&spec, &cfg, &[&data.histories[0]]);
    let (x, _) = set
        .sample(2, 12, &mut ChaCha8Rng::seed_from_u64(0))
        .unwrap();
    let full = model.forward_t(&x, false).unwrap();
    let mut cache = model.transformer.new_cache();
    let steps: Vec<Tensor> = (0..12)
        .map(|t| model.forward_step(&x.narrow(1, t, 1), &mut cache).unwrap())
        .collect();
    let stepped = Tensor::cat(&steps, 1);
    let diff = (full - stepped).abs().max().double_value(&[]);
    assert!(diff < 1e-4, "{diff}");
}

#[test]
fn trains_on_a_merged_file_of_shards() {
    use crate::data::histories::{Shard, read_histories, write_histories};
    let dir = fresh_dir("merged");
    fs::create_dir_all(&dir).unwrap();
    let mut d = DatasetConfig::paper(EnvName::DarkRoom, 2, 11);
    d.source = Source::NoisyOptimal;
    d.steps = 600;
    d.cost_limits = vec![0.0, 5.0];
    let whole = generate(&d, &|_| {}).unwrap().file;
    let shards: Vec<PathBuf> = (0..2)
        .map(|index| {
            d.shard = Some(Shard { index, count: 2 });
            let path = dir.join(format!("part{index}.h5"));
            write_histories(&path, &generate(&d, &|_| {}).unwrap().file).unwrap();
            path
        })
        .collect();
    let merged = dir.join("all.h5");
    let existing = safety_envs::output::Existing::Refuse;
    crate::data::merge::merge(&merged, &shards, existing).unwrap();
    assert_eq!(
        read_histories(&merged, Some("darkroom")).unwrap().histories,
        whole.histories
    );
    // The learner's own entry point, as `icrl pretrain --method ad --dataset all.h5`.
    let sets: Vec<String> = [
        "updates=4",
        "checkpoint_every=2",
        "batch_size=4",
        "torch_threads=1",
        "model.n_layers=1",
        "model.d_model=32",
        "model.d_ff=64",
    ]
    .map(String::from)
    .to_vec();
    let s = crate::cli::pretrain::ad(
        "darkroom",
        "quick",
        Some(&merged),
        None,
        &sets,
        &dir.join("runs"),
    )
    .unwrap();
    assert_eq!(s.updates, 4);
    assert_eq!(s.train_histories + s.val_histories, 4);
    let _ = fs::remove_dir_all(&dir);
}
