//! Bad inputs and faults across learners (issue 12: nothing silently wrong,
//! nothing lost). One test per class; RELIABILITY.md maps each bad input to
//! the test that covers it.

use std::fs;
use std::path::{Path, PathBuf};

use safety_envs::EnvName;
use tch::Tensor;

use crate::ad::{self, AdConfig, AdError, TrainRequest};
use crate::checkpoint::{MANIFEST, Manifest, sha256_file};
use crate::data::dataset::{DatasetConfig, Source, generate};
use crate::data::histories::HistoryFile;
use crate::eppo::{self, EppoError, Learner, PretrainOptions};

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("icrl-reliability-{name}-{}", std::process::id()));
    let _ = fs::remove_dir_all(&d);
    fs::create_dir_all(&d).unwrap();
    d
}

/// `icrl pretrain --env darkroom --set ...` as the CLI runs it.
fn pretrain_err(out: &Path, sets: &[&str]) -> String {
    let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
    crate::cli::pretrain::eppo("darkroom", "quick", None, &sets, out)
        .expect_err("refused")
        .to_string()
}

/// Rewrites a checkpoint's manifest so it vouches for the files as they are
/// now (what an older build would have written with bad weights).
fn reseal(ckpt: &Path) {
    let mut m: Manifest =
        serde_json::from_str(&fs::read_to_string(ckpt.join(MANIFEST)).unwrap()).unwrap();
    for (name, size) in m.files.iter_mut() {
        *size = fs::metadata(ckpt.join(name)).unwrap().len();
        m.sha256
            .insert(name.clone(), sha256_file(&ckpt.join(name)).unwrap());
    }
    fs::write(ckpt.join(MANIFEST), serde_json::to_string(&m).unwrap()).unwrap();
}

/// Sets every value of the first tensor of a safetensors file to NaN.
fn poison(file: &Path) -> String {
    let mut named = Tensor::read_safetensors(file).unwrap();
    named.sort_by(|a, b| a.0.cmp(&b.0));
    let _ = named[0].1.fill_(f64::NAN);
    Tensor::write_safetensors(&named, file).unwrap();
    named[0].0.clone()
}

fn tiny_eppo(total_updates: u64) -> eppo::EppoConfig {
    {
        let mut c = eppo::tests::tiny();
        c.optimisation.total_updates = total_updates;
        c.run.checkpoint_every = 1;
        c.run.keep_checkpoints = 0;
        c
    }
}

fn tiny_ad_data() -> HistoryFile {
    let mut d = DatasetConfig::paper(EnvName::DarkRoom, 2, 11);
    d.source = Source::NoisyOptimal;
    d.steps = 600;
    d.cost_limits = vec![0.0];
    generate(&d, &|_| {}).unwrap().file
}

fn tiny_ad_cfg() -> AdConfig {
    let mut cfg = AdConfig::preset("darkroom-quick").unwrap();
    cfg.model.n_layers = 1;
    cfg.model.d_model = 16;
    cfg.model.n_heads = 2;
    cfg.model.d_ff = 32;
    cfg.model.max_len = 20;
    cfg.batch_size = 4;
    cfg.updates = 6;
    cfg.log_every = 2;
    cfg.checkpoint_every = 3;
    cfg.val_fraction = 0.0;
    cfg
}

fn ad_train(
    cfg: &AdConfig,
    data: &HistoryFile,
    dir: &Path,
    resume: Option<&Path>,
) -> Result<ad::TrainSummary, AdError> {
    ad::train(
        &TrainRequest {
            cfg,
            data,
            dataset_path: Path::new("tiny.h5"),
            run_dir: dir,
            resume,
        },
        &mut |_| {},
        &mut |_| {},
    )
}

/// Class 1 and 2 for EPPO: NaN, negative and zero settings, and settings
/// that cannot fit in memory, are refused before anything is allocated or
/// any run folder is made, naming the setting and its range.
#[test]
fn eppo_settings_are_checked_before_anything_runs() {
    let out = tmp("eppo-settings").join("runs");
    let cases: [(&[&str], &[&str]); 11] = [
        // tau = 0: the target networks would never move.
        (&["tau=0"], &["tau = 0: must be a finite number in (0, 1]"]),
        (
            &["torch_threads=100000"],
            &["torch_threads = 100000: must be in [0, 1024]"],
        ),
        (
            &["lr=nan"],
            &["lr = NaN: must be a finite number in (0, 1]"],
        ),
        (&["lr=-1"], &["lr = -1: must be a finite number in (0, 1]"]),
        (&["entropy_coef=nan"], &["entropy_coef = NaN", "[0, inf)"]),
        (
            &["updates_per_round=0"],
            &["updates_per_round = 0: must be at least 1"],
        ),
        (
            &["checkpoint_every=0"],
            &["checkpoint_every = 0: must be at least 1"],
        ),
        (
            &["batch_size=1000000000"],
            &[
                "needs about",
                "one batch's activations",
                "available",
                "/proc/meminfo",
            ],
        ),
        (&["model.d_model=1000000"], &["needs about", "parameters"]),
        (
            &["model.max_len=1000000000"],
            &["needs about", "lower batch_size, model.max_len"],
        ),
        (&["n_envs=1000000"], &["needs about", "acting cache"]),
    ];
    for (sets, wants) in cases {
        let e = pretrain_err(&out, sets);
        for w in wants {
            assert!(e.contains(w), "{sets:?}: {e}");
        }
    }
    assert!(!out.exists(), "no run folder for a refused configuration");
    fs::remove_dir_all(out.parent().unwrap()).unwrap();
}

/// A name, a change to a valid AD config, and the error it must give.
type AdCase = (&'static str, fn(&mut AdConfig), &'static str);

/// Class 1 and 2 for AD: the same checks, and data that holds NaN or an
/// action outside the action space is refused before training.
#[test]
fn ad_settings_and_data_are_checked_before_training() {
    let dir = tmp("ad-settings");
    let data = tiny_ad_data();
    let cases: [AdCase; 6] = [
        (
            "lr",
            |c| c.learning_rate = f64::NAN,
            "learning_rate = NaN: must be a finite number in (0, 1]",
        ),
        (
            "beta2",
            |c| c.beta2 = 1.0,
            "beta2 = 1: must be a finite number in [0, 1)",
        ),
        (
            "clip",
            |c| c.grad_clip = -1.0,
            "grad_clip = -1: must be a finite number in (0, inf)",
        ),
        (
            "ckpt",
            |c| c.checkpoint_every = 0,
            "checkpoint_every = 0: must be at least 1",
        ),
        ("batch", |c| c.batch_size = 1_000_000_000, "needs about"),
        ("len", |c| c.model.max_len = 1_000_000_000, "needs about"),
    ];
    for (name, set, want) in cases {
        let mut cfg = tiny_ad_cfg();
        set(&mut cfg);
        let e = ad_train(&cfg, &data, &dir.join(name), None)
            .unwrap_err()
            .to_string();
        assert!(e.contains(want), "{name}: {e}");
        assert!(
            !dir.join(name).join("checkpoints").exists(),
            "{name}: nothing written"
        );
    }
    let mut nan = data.clone();
    nan.histories[0].rewards[5] = f32::NAN;
    let e = ad_train(&tiny_ad_cfg(), &nan, &dir.join("nan"), None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("tiny.h5") && e.contains("rewards holds NaN at step 5"),
        "{e}"
    );
    let mut bad_action = data.clone();
    bad_action.histories[1].actions[3] = 17.0;
    let e = ad_train(&tiny_ad_cfg(), &bad_action, &dir.join("act"), None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("action 17 at step 3 is not one of the 5 discrete actions"),
        "{e}"
    );
    fs::remove_dir_all(&dir).unwrap();
}

/// Class 1: a NaN loss is never applied; EPPO stops naming the update, and
/// a checkpoint holding NaN weights is refused on resume and on eval.
#[test]
fn eppo_non_finite_values_stop_training_and_are_refused_on_load() {
    let root = tmp("eppo-nan");
    let run = eppo::train(&PretrainOptions {
        env: EnvName::DarkRoom,
        cfg: tiny_eppo(2),
        out: root.clone(),
        resume: None,
        progress: false,
    })
    .unwrap();
    let ckpt = run.last_checkpoint.clone();
    // A learner whose weights went NaN: the update is refused, nothing moves.
    let mut learner = Learner::resume(tiny_eppo(2), EnvName::DarkRoom, &ckpt).unwrap();
    let mut venv = safety_envs::VecEnv::new(
        (0..3)
            .map(|_| {
                safety_envs::make_env(
                    EnvName::DarkRoom,
                    &safety_envs::EnvOptions {
                        max_episode_steps: Some(6),
                        ..Default::default()
                    },
                )
            })
            .collect::<Result<Vec<_>, _>>()
            .unwrap(),
        1,
        true,
    )
    .unwrap();
    learner.collect(&mut venv).unwrap();
    let mut vars = learner.vs.variables().into_iter().collect::<Vec<_>>();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    let (poisoned, other) = (&vars[vars.len() - 1].1, &vars[0].1);
    tch::no_grad(|| {
        let _ = poisoned.shallow_clone().fill_(f64::NAN);
    });
    let before = Vec::<f32>::try_from(other.flatten(0, -1)).unwrap();
    let steps = learner.opt.step_count();
    let e = learner.update().unwrap_err();
    assert!(matches!(&e, EppoError::NonFinite { update: 3, .. }), "{e}");
    assert!(e.to_string().contains("update 3: the loss is NaN"), "{e}");
    assert_eq!(learner.updates, 2);
    assert_eq!(learner.opt.step_count(), steps, "no Adam step taken");
    assert_eq!(Vec::<f32>::try_from(other.flatten(0, -1)).unwrap(), before);

    // A checkpoint of NaN weights (sealed as an older build would have):
    // resume and evaluation refuse it, naming the weight.
    let name = poison(&ckpt.join("model.safetensors"));
    reseal(&ckpt);
    let e = Learner::resume(tiny_eppo(4), EnvName::DarkRoom, &ckpt)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains(&format!("weight {name} holds")) && e.contains("NaN"),
        "{e}"
    );
    let e = crate::eval::load::load_checkpoint(&ckpt, EnvName::DarkRoom)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("NaN or infinite") && e.contains("cannot act"),
        "{e}"
    );
    fs::remove_dir_all(&root).unwrap();
}

/// Class 1 for AD: finite but absurd data whose return-to-go overflows
/// float32 makes the loss NaN: training stops before applying it, names the
/// update and the last good checkpoint, and writes no checkpoint after it.
/// NaN weights are refused by evaluation.
#[test]
fn ad_non_finite_loss_stops_naming_the_last_good_checkpoint() {
    let dir = tmp("ad-nan");
    let data = tiny_ad_data();
    let cfg = tiny_ad_cfg();
    ad_train(&cfg, &data, &dir, None).unwrap();
    let step_6 = dir.join("checkpoints/step_6");
    // Every reward 3e38: finite, but an episode's return-to-go is not.
    let mut huge = data.clone();
    for h in &mut huge.histories {
        h.rewards.iter_mut().for_each(|r| *r = 3e38);
    }
    let mut more = cfg.clone();
    more.updates = 12;
    let e = ad_train(&more, &huge, &dir, Some(&step_6)).unwrap_err();
    assert!(matches!(&e, AdError::NonFinite { update: 7, .. }), "{e}");
    let e = e.to_string();
    assert!(
        e.contains("update 7: the loss is NaN")
            && e.contains(&format!("last good checkpoint is {}", step_6.display())),
        "{e}"
    );
    assert!(!dir.join("checkpoints/step_7").exists() && !dir.join("checkpoints/step_9").exists());
    // NaN weights (sealed as an older build would have) are refused.
    let name = poison(&step_6.join("model.safetensors"));
    reseal(&step_6);
    let e = ad::AdAgent::load(&dir).err().unwrap().to_string();
    assert!(e.contains(&format!("weight {name} holds")), "{e}");
    let e = crate::eval::load::load_checkpoint(&dir, EnvName::DarkRoom)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("NaN or infinite"), "{e}");
    let e = ad_train(&more, &data, &dir, Some(&step_6))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("NaN or infinite"),
        "resume refuses NaN weights too: {e}"
    );
    fs::remove_dir_all(&dir).unwrap();
}

/// Class 4 in-process: a stop request ends EPPO and AD after the current
/// update with a checkpoint; resuming continues without counting an update
/// twice in metrics.jsonl.
#[test]
fn a_stop_request_checkpoints_and_the_run_resumes() {
    let root = tmp("stop");
    let mut cfg = tiny_eppo(4);
    cfg.run.checkpoint_every = 100;
    let (done, updates) = eppo::tests::stop_after_one_then_resume(&cfg, &root);
    assert_eq!(done, 4);
    assert_eq!(
        updates,
        vec![1, 3, 4],
        "one record per round, none repeated"
    );

    // AD: stops after update 1 with step_1 written.
    let data = tiny_ad_data();
    let ad_dir = root.join("ad");
    crate::stop::request();
    let e = ad_train(&tiny_ad_cfg(), &data, &ad_dir, None).unwrap_err();
    crate::stop::clear();
    let AdError::Interrupted {
        checkpoint,
        updates,
    } = e
    else {
        panic!("{e}");
    };
    assert_eq!(
        (updates, checkpoint.clone()),
        (1, ad_dir.join("checkpoints/step_1"))
    );
    let s = ad_train(&tiny_ad_cfg(), &data, &ad_dir, Some(&checkpoint)).unwrap();
    assert_eq!((s.resumed_from, s.updates), (1, 6));
    fs::remove_dir_all(&root).unwrap();
}

/// The memory estimate must not refuse what the project ships: every preset
/// (the paper's GPU presets included, run on the CPU) fits in 16 GB.
#[test]
fn every_shipped_preset_fits_the_memory_estimate() {
    for env in EnvName::ALL {
        let probe = safety_envs::make_env(env, &safety_envs::EnvOptions::default()).unwrap();
        let spec =
            eppo::NetSpec::from_spaces(&probe.observation_space(), &probe.action_space()).unwrap();
        for preset in ["quick", "table1"] {
            let table = crate::presets::preset_table("eppo", env.as_str(), preset).unwrap();
            let cfg = eppo::EppoConfig::from_table("preset", table).unwrap();
            let m = eppo::memory_estimate(&cfg, &spec);
            assert!(m.total() < 16e9, "eppo {env} {preset}: {m:?}");
        }
        for preset in ["quick", "table2"] {
            let cfg = AdConfig::preset(&format!("{env}-{preset}")).unwrap();
            let spec = ad::AdSpec {
                env: env.as_str().into(),
                obs_dim: spec.obs_dim,
                action_dim: spec.act_flat(),
                discrete: spec.n_actions.is_some(),
                obs_mean: vec![0.0; spec.obs_dim],
                obs_std: vec![1.0; spec.obs_dim],
                dataset: String::new(),
                dataset_config: String::new(),
                pretrain_tasks: None,
                physics_steps_per_action: None,
                token: Some(ad::TOKEN_LAYOUT.into()),
            };
            // A paper-sized dataset: 100 tasks x 3 limits x 50k steps.
            let m = ad::memory_estimate(&cfg, &spec, 15_000_000);
            assert!(m.total() < 16e9, "ad {env} {preset}: {m:?}");
        }
    }
}

/// Class 1 and 2 for PPO-Lagrangian (the learner behind `icrl dataset`).
#[test]
fn ppo_lagrangian_settings_are_checked() {
    use crate::ppo_lagrangian::PpoLagConfig;
    type Case = (fn(&mut PpoLagConfig), &'static str);
    let cases: [Case; 5] = [
        (
            |c| c.learning_rate = f64::NAN,
            "learning_rate = NaN: must be a finite number in (0, 1]",
        ),
        (
            |c| c.ent_coef = -0.1,
            "ent_coef = -0.1: must be a finite number in [0, inf)",
        ),
        (|c| c.max_grad_norm = f64::INFINITY, "max_grad_norm = inf"),
        (|c| c.minibatches = 0, "minibatches = 0: must be at least 1"),
        (
            |c| c.update_epochs = 0,
            "update_epochs = 0: must be at least 1",
        ),
    ];
    for (set, want) in cases {
        let mut cfg = PpoLagConfig::darkroom();
        set(&mut cfg);
        let e = cfg.validate().unwrap_err().to_string();
        assert!(e.contains(want), "{e}");
    }
    PpoLagConfig::darkroom().validate().unwrap();
    PpoLagConfig::mujoco().validate().unwrap();
}
