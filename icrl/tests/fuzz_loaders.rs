//! Fuzz harness for the three loaders that read user files: MJCF through the
//! `safety_envs::mujoco::Model` wrapper, the HDF5 history reader, and the
//! checkpoint loaders (EPPO and AD). Real files are mutated (truncation, byte
//! flips and runs, duplicated and deleted chunks, swapped dtypes, huge
//! declared sizes, absurd numbers) from a seeded generator; every case must
//! end in `Ok` or a typed error: no panic, abort or hang (a watchdog fails
//! the run if one case takes over a minute).
//!
//! Cases per loader: `ICRL_FUZZ_CASES` (default 40, which keeps CI under a
//! minute). A longer run, e.g. before a release:
//! `ICRL_FUZZ_CASES=5000 cargo test --release -p icrl --test fuzz_loaders`;
//! `ICRL_FUZZ_SEED` picks another stream of cases; `ICRL_FUZZ_VERBOSE=1`
//! names each case before it runs.

use std::fmt::Display;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Duration;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use safety_envs::EnvName;

fn cases() -> usize {
    std::env::var("ICRL_FUZZ_CASES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(40)
}

fn seed() -> u64 {
    std::env::var("ICRL_FUZZ_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(12)
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("icrl-fuzz-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Runs one case: a panic fails with the case's description; a case that
/// runs over a minute ends the process (a hang must not block CI).
fn run_case<T, E: Display>(
    what: &str,
    case: usize,
    desc: &str,
    f: impl FnOnce() -> Result<T, E>,
) -> bool {
    let (done, wait) = mpsc::channel::<()>();
    let label = format!("{what} case {case} ({desc})");
    // Names each case before it runs: the last line before a crash of the
    // C libraries (which no catch_unwind can stop) is the culprit.
    if std::env::var_os("ICRL_FUZZ_VERBOSE").is_some() {
        eprintln!("fuzz: {label}");
    }
    let watchdog_label = label.clone();
    std::thread::spawn(move || {
        if wait.recv_timeout(Duration::from_secs(60)) == Err(mpsc::RecvTimeoutError::Timeout) {
            eprintln!("fuzz: {watchdog_label} hung for a minute");
            std::process::exit(3);
        }
    });
    let result = catch_unwind(AssertUnwindSafe(f));
    let _ = done.send(());
    match result {
        Ok(r) => r.is_ok(),
        Err(p) => {
            let msg = p
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_default();
            panic!("fuzz: {label} panicked: {msg}");
        }
    }
}

/// One random byte-level mutation of `bytes`, described.
fn mutate_bytes(rng: &mut ChaCha8Rng, bytes: &mut Vec<u8>) -> String {
    let n = bytes.len().max(1);
    match rng.gen_range(0..6) {
        0 => {
            let at = rng.gen_range(0..n);
            bytes.truncate(at);
            format!("truncated to {at} bytes")
        }
        1 => {
            let k = rng.gen_range(1..=8);
            for _ in 0..k {
                let at = rng.gen_range(0..n);
                if let Some(b) = bytes.get_mut(at) {
                    *b ^= 1 << rng.gen_range(0..8);
                }
            }
            format!("{k} bit flips")
        }
        2 => {
            let at = rng.gen_range(0..n);
            let len = rng.gen_range(1..=64).min(bytes.len().saturating_sub(at));
            let v = if rng.r#gen() { 0xff } else { 0x00 };
            bytes[at..at + len].fill(v);
            format!("{len} bytes at {at} set to {v:#x}")
        }
        3 => {
            let at = rng.gen_range(0..n).min(bytes.len());
            let len = rng.gen_range(1..=256).min(bytes.len() - at);
            let chunk = bytes[at..at + len].to_vec();
            bytes.splice(at..at, chunk);
            format!("{len} bytes at {at} duplicated")
        }
        4 => {
            let at = rng.gen_range(0..n).min(bytes.len());
            let len = rng.gen_range(1..=256).min(bytes.len() - at);
            bytes.drain(at..at + len);
            format!("{len} bytes at {at} deleted")
        }
        _ => {
            let at = rng.gen_range(0..n).min(bytes.len());
            let junk: Vec<u8> = (0..rng.gen_range(1..=32)).map(|_| rng.r#gen()).collect();
            let len = junk.len();
            bytes.splice(at..at, junk);
            format!("{len} random bytes inserted at {at}")
        }
    }
}

/// Numbers that break assumptions.
const ABSURD: [&str; 10] = [
    "nan",
    "inf",
    "-inf",
    "-1",
    "0",
    "1e308",
    "-1e308",
    "99999999999",
    "4294967296",
    "",
];

/// Replaces the `k`-th number in `text` by an absurd one.
fn mutate_number(rng: &mut ChaCha8Rng, text: &str) -> (String, String) {
    let spans: Vec<(usize, usize)> = {
        let b = text.as_bytes();
        let mut out = Vec::new();
        let mut i = 0;
        while i < b.len() {
            if b[i].is_ascii_digit() {
                let s = i;
                while i < b.len() && (b[i].is_ascii_digit() || b[i] == b'.' || b[i] == b'e') {
                    i += 1;
                }
                out.push((s, i));
            } else {
                i += 1;
            }
        }
        out
    };
    if spans.is_empty() {
        return (text.to_string(), "no number to replace".into());
    }
    let (s, e) = spans[rng.gen_range(0..spans.len())];
    let new = ABSURD[rng.gen_range(0..ABSURD.len())];
    (
        format!("{}{new}{}", &text[..s], &text[e..]),
        format!("number {:?} at {s} -> {new:?}", &text[s..e]),
    )
}

#[test]
fn mjcf_loader_survives_mutated_models() {
    let files = [
        ("point.xml", include_str!("../../assets/xml/point.xml")),
        ("car.xml", include_str!("../../assets/xml/car.xml")),
        ("arena.xml", include_str!("../../assets/xml/arena.xml")),
    ];
    let mut rng = ChaCha8Rng::seed_from_u64(seed());
    let mut ok = 0;
    for case in 0..cases() {
        let (name, text) = files[case % files.len()];
        let (xml, desc) = if rng.r#gen() {
            mutate_number(&mut rng, text)
        } else {
            let mut bytes = text.as_bytes().to_vec();
            let d = mutate_bytes(&mut rng, &mut bytes);
            (String::from_utf8_lossy(&bytes).into_owned(), d)
        };
        ok += usize::from(run_case(name, case, &desc, || {
            let model = safety_envs::mujoco::Model::from_xml_str(&xml)?;
            let mut data = safety_envs::mujoco::Data::new(&model)?;
            for _ in 0..10 {
                data.step(&model)?;
            }
            Ok::<_, safety_envs::MujocoError>(())
        }));
    }
    eprintln!("mjcf: {ok} of {} mutated models still loaded", cases());
}

/// A small valid history file, written by the real writer.
fn history_file(path: &Path) {
    use icrl::data::histories::{DatasetInfo, History, HistoryFile, write_histories};
    let spawn = safety_envs::SpawnConfig::darkroom();
    let histories: Vec<History> = (0..3)
        .map(|i| {
            let task =
                safety_envs::sample_task(&spawn, safety_envs::Orientation::Centre, i).unwrap();
            let mut h = History::new(task, i as f32);
            for t in 0..12 {
                let x = t as f32;
                h.push(
                    &[x, -x],
                    &[(t % 5) as f32],
                    0.5,
                    (t % 2) as f32,
                    &[x + 1.0, -x],
                    t == 5,
                    t == 11,
                );
            }
            h
        })
        .collect();
    write_histories(
        path,
        &HistoryFile {
            info: DatasetInfo {
                env: "darkroom".into(),
                config: "{}".into(),
                seed: 1,
                obs_dim: 2,
                action_dim: 1,
                action_n: Some(5),
                grid_size: 9,
                physics_steps_per_action: None,
                grid_histories: histories.len(),
                shard: None,
            },
            histories,
        },
    )
    .unwrap();
}

/// One structural mutation through the HDF5 API: swapped dtypes, huge
/// declared sizes, wrong shapes, missing datasets, absurd attributes. The
/// file's checksum line is then cleared (a file written elsewhere), so the
/// reader's own checks, not the checksum, meet the mutation.
fn mutate_hdf5(rng: &mut ChaCha8Rng, path: &Path) -> String {
    let desc = mutate_hdf5_objects(rng, path);
    let mut bytes = std::fs::read(path).unwrap();
    bytes[..64].fill(0);
    std::fs::write(path, bytes).unwrap();
    desc
}

fn mutate_hdf5_objects(rng: &mut ChaCha8Rng, path: &Path) -> String {
    let f = hdf5::File::open_rw(path).unwrap();
    let names = [
        "observations",
        "next_observations",
        "actions",
        "rewards",
        "costs",
        "terminals",
        "timeouts",
        "history_id",
        "episode_id",
        "cost_limit",
        "task_goal",
        "task_obstacles",
    ];
    let name = names[rng.gen_range(0..names.len())];
    let shape = f.dataset(name).map(|d| d.shape()).unwrap_or_default();
    let rows = shape.first().copied().unwrap_or(0);
    match rng.gen_range(0..7) {
        0 => {
            f.unlink(name).unwrap();
            let n: usize = shape.iter().product();
            f.new_dataset::<f64>()
                .shape(shape.clone())
                .create(name)
                .unwrap()
                .write_raw(&vec![1.5f64; n])
                .unwrap();
            format!("{name} rewritten as float64")
        }
        1 => {
            f.unlink(name).unwrap();
            let n: usize = shape.iter().product();
            f.new_dataset::<i8>()
                .shape(shape.clone())
                .create(name)
                .unwrap()
                .write_raw(&vec![-3i8; n])
                .unwrap();
            format!("{name} rewritten as int8")
        }
        2 => {
            // Chunked and empty: the declared size costs nothing on disk.
            f.unlink(name).unwrap();
            let mut huge = shape.clone();
            huge[0] = 1 << 40;
            f.new_dataset::<f32>()
                .shape(huge.clone())
                .chunk(vec![1; huge.len()])
                .create(name)
                .unwrap();
            format!("{name} declared with shape {huge:?}")
        }
        3 => {
            f.unlink(name).unwrap();
            let mut s = shape.clone();
            s[0] = rows + rng.gen_range(1..5);
            let n: usize = s.iter().product();
            f.new_dataset::<f32>()
                .shape(s.clone())
                .create(name)
                .unwrap()
                .write_raw(&vec![0f32; n])
                .unwrap();
            format!("{name} with {} rows instead of {rows}", s[0])
        }
        4 => {
            f.unlink(name).unwrap();
            format!("{name} removed")
        }
        5 => {
            let attr =
                ["obs_dim", "action_dim", "action_n", "grid_size", "seed"][rng.gen_range(0..5)];
            let v: u64 = [0, 1, 1 << 40, u64::MAX][rng.gen_range(0..4)];
            f.attr(attr).unwrap().write_scalar(&v).unwrap();
            format!("attribute {attr} = {v}")
        }
        _ => {
            let ids =
                ["history_id", "task_goal", "task_obstacles", "episode_id"][rng.gen_range(0..4)];
            let d = f.dataset(ids).unwrap();
            let s = d.shape();
            let n: usize = s.iter().product();
            let v: i64 = [-1, i64::MAX, 1 << 40, 7][rng.gen_range(0..4)];
            let mut data = d.read_raw::<i64>().unwrap();
            if n > 0 {
                let at = rng.gen_range(0..n);
                data[at] = v;
            }
            f.unlink(ids).unwrap();
            f.new_dataset::<i64>()
                .shape(s)
                .create(ids)
                .unwrap()
                .write_raw(&data)
                .unwrap();
            format!("one value of {ids} set to {v}")
        }
    }
}

#[test]
fn history_reader_survives_mutated_files() {
    let dir = tmp("h5");
    let good = dir.join("good.h5");
    history_file(&good);
    let bytes = std::fs::read(&good).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(seed() ^ 0x4835);
    let mut ok = 0;
    for case in 0..cases() {
        let path = dir.join(format!("case{case}.h5"));
        let desc = if rng.r#gen() {
            let mut b = bytes.clone();
            let d = mutate_bytes(&mut rng, &mut b);
            std::fs::write(&path, b).unwrap();
            d
        } else {
            std::fs::copy(&good, &path).unwrap();
            mutate_hdf5(&mut rng, &path)
        };
        ok += usize::from(run_case("history file", case, &desc, || {
            icrl::data::histories::read_histories(&path, Some("darkroom"))
        }));
        let _ = std::fs::remove_file(&path);
    }
    eprintln!("hdf5: {ok} of {} mutated files still read", cases());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Copies a folder (flat, or one level of subfolders).
fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.path().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

/// Makes the manifest vouch for the files as they are (so a mutation reaches
/// the parsers behind the checksum, as in a file written by a buggy build).
fn reseal(ckpt: &Path) {
    let path = ckpt.join("manifest.json");
    let Ok(text) = std::fs::read_to_string(&path) else {
        return;
    };
    let Ok(mut m) = serde_json::from_str::<icrl::checkpoint::Manifest>(&text) else {
        return;
    };
    for (name, size) in m.files.iter_mut() {
        if let Ok(meta) = std::fs::metadata(ckpt.join(name)) {
            *size = meta.len();
            if let Ok(h) = icrl::checkpoint::sha256_file(&ckpt.join(name)) {
                m.sha256.insert(name.clone(), h);
            }
        }
    }
    std::fs::write(&path, serde_json::to_string(&m).unwrap()).unwrap();
}

/// A mutation of a safetensors header: its JSON (dtype, shape, offsets) or
/// its declared length.
fn mutate_safetensors(rng: &mut ChaCha8Rng, bytes: &mut Vec<u8>) -> String {
    if bytes.len() < 8 {
        return "too short to parse".into();
    }
    let len = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    if rng.gen_range(0..4) == 0 || 8 + len > bytes.len() {
        let v: u64 = [0, 1, 1 << 40, u64::MAX][rng.gen_range(0..4)];
        bytes[..8].copy_from_slice(&v.to_le_bytes());
        return format!("header length {v}");
    }
    let header = String::from_utf8_lossy(&bytes[8..8 + len]).into_owned();
    let (new, desc) = match rng.gen_range(0..3) {
        0 => (
            header.replacen(
                "\"F32\"",
                ["\"I64\"", "\"F64\"", "\"BOOL\"", "\"U8\""][rng.gen_range(0..4)],
                1,
            ),
            "dtype swapped".to_string(),
        ),
        1 => mutate_number(rng, &header),
        _ => (
            header.replacen("[", "[1099511627776,", 1),
            "a huge dimension added".to_string(),
        ),
    };
    let mut out = (new.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(new.as_bytes());
    out.extend_from_slice(&bytes[8 + len..]);
    *bytes = out;
    format!("safetensors header: {desc}")
}

/// A small EPPO checkpoint and a small AD run, trained for real (with the
/// EPPO run's configuration, for resuming it).
fn checkpoints(root: &Path) -> (PathBuf, PathBuf, icrl::eppo::EppoConfig) {
    let sets: Vec<String> = [
        "max_episode_steps=6",
        "k_min=2",
        "k_max=2",
        "n_envs=2",
        "batch_size=2",
        "replay_capacity=1000",
        "encoder_hidden=8",
        "head_hidden=8",
        "model.d_model=8",
        "model.n_heads=2",
        "model.n_layers=1",
        "model.d_ff=16",
        "model.max_len=12",
        "total_updates=1",
        "updates_per_round=1",
        "learning_starts=0",
        "checkpoint_every=1",
    ]
    .map(String::from)
    .to_vec();
    let mut table = icrl::presets::preset_table("eppo", "darkroom", "quick").unwrap();
    icrl::eppo::EppoConfig::apply_sets(&mut table, &sets).unwrap();
    let cfg = icrl::eppo::EppoConfig::from_table("fuzz", table).unwrap();
    let eppo_cfg = cfg.clone();
    let eppo = icrl::eppo::train(&icrl::eppo::PretrainOptions {
        env: EnvName::DarkRoom,
        cfg,
        out: root.join("eppo"),
        resume: None,
        progress: false,
    })
    .unwrap()
    .run_dir;
    let mut d = icrl::data::dataset::DatasetConfig::paper(EnvName::DarkRoom, 1, 3);
    d.source = icrl::data::dataset::Source::NoisyOptimal;
    d.steps = 300;
    d.cost_limits = vec![0.0];
    let data = icrl::data::dataset::generate(&d, &|_| {}).unwrap().file;
    let mut cfg = icrl::ad::AdConfig::preset("darkroom-quick").unwrap();
    cfg.model.n_layers = 1;
    cfg.model.d_model = 8;
    cfg.model.n_heads = 2;
    cfg.model.d_ff = 16;
    cfg.model.max_len = 10;
    cfg.batch_size = 2;
    cfg.updates = 1;
    cfg.checkpoint_every = 1;
    cfg.val_fraction = 0.0;
    let ad = root.join("ad");
    icrl::ad::train(
        &icrl::ad::TrainRequest {
            cfg: &cfg,
            data: &data,
            dataset_path: Path::new("fuzz.h5"),
            run_dir: &ad,
            resume: None,
        },
        &mut |_| {},
        &mut |_| {},
    )
    .unwrap();
    (eppo, ad, eppo_cfg)
}

#[test]
fn checkpoint_loaders_survive_mutated_checkpoints() {
    let root = tmp("ckpt");
    let (eppo, ad, eppo_cfg) = checkpoints(&root);
    let mut rng = ChaCha8Rng::seed_from_u64(seed() ^ 0xc4e7);
    let mut ok = 0;
    for case in 0..cases() {
        let is_ad = case % 2 == 1;
        let run = root.join(format!("case{case}"));
        copy_dir(if is_ad { &ad } else { &eppo }, &run);
        let ckpt = std::fs::read_dir(run.join("checkpoints"))
            .unwrap()
            .filter_map(|e| e.ok().map(|e| e.path()))
            .find(|p| {
                p.file_name()
                    .is_some_and(|n| n.to_string_lossy().starts_with("step_"))
            })
            .unwrap();
        let candidates: Vec<PathBuf> = [
            ckpt.join("model.safetensors"),
            ckpt.join("manifest.json"),
            ckpt.join("state.json"),
            if is_ad {
                ckpt.join("adam.safetensors")
            } else {
                ckpt.join("config.toml")
            },
            if is_ad {
                run.join("spec.json")
            } else {
                ckpt.join("optimizer.safetensors")
            },
            run.join("config.toml"),
            ckpt.join("replay.safetensors"),
        ]
        .into_iter()
        .filter(|p| p.exists())
        .collect();
        let file = &candidates[rng.gen_range(0..candidates.len())];
        let mut bytes = std::fs::read(file).unwrap();
        let is_tensors = file.extension().is_some_and(|e| e == "safetensors");
        let text_like = !is_tensors && rng.r#gen::<bool>();
        let mut desc = if is_tensors && rng.r#gen() {
            mutate_safetensors(&mut rng, &mut bytes)
        } else if text_like {
            let (t, d) = mutate_number(&mut rng, &String::from_utf8_lossy(&bytes));
            bytes = t.into_bytes();
            d
        } else {
            mutate_bytes(&mut rng, &mut bytes)
        };
        std::fs::write(file, bytes).unwrap();
        if rng.r#gen() {
            reseal(&ckpt);
            desc.push_str(", manifest resealed");
        }
        let desc = format!("{}: {desc}", file.strip_prefix(&root).unwrap().display());
        ok += usize::from(run_case("checkpoint", case, &desc, || {
            icrl::eval::load::load_checkpoint(&run, EnvName::DarkRoom).map(|_| ())
        }));
        // Resuming reads the optimizer's moments too.
        if !is_ad {
            run_case("resume", case, &desc, || {
                icrl::eppo::Learner::resume(eppo_cfg.clone(), EnvName::DarkRoom, &ckpt).map(|_| ())
            });
        }
        let _ = std::fs::remove_dir_all(&run);
    }
    eprintln!(
        "checkpoints: {ok} of {} mutated checkpoints still loaded",
        cases()
    );
    std::fs::remove_dir_all(&root).unwrap();
}
