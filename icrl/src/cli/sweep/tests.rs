use std::path::{Path, PathBuf};

use crate::cli::pretrain::{InOut, run_in_out};

use super::slurm::slurm_time;
use super::*;

pub(super) fn grid_file(dir: &Path, text: &str) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    let path = dir.join("sweep.toml");
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn the_array_has_one_task_per_seed_and_setting() {
    let dir = std::env::temp_dir().join(format!("icrl-sweep-grid-{}", std::process::id()));
    let path = grid_file(
        &dir,
        r#"
env = "darkroom"
seeds = [0, 1]
out = "sweep"
[set]
total_updates = 600
[grid]
lr = [1e-4, 3e-4]
k_max = [16]
[slurm]
partition = "cpu"
account = "proj"
"#,
    );
    let grid = SweepGrid::load(&path).unwrap();
    let tasks = grid.tasks();
    assert_eq!(tasks.len(), 4);
    assert_eq!(tasks[1].seed, 1);
    assert_eq!(tasks[1].label(), "k_max=16 lr=0.0001");
    assert_eq!(tasks[2].label(), "k_max=16 lr=0.0003");
    let args = grid.pretrain_args(&tasks[3]).join(" ");
    assert!(
        args.contains("--set total_updates=600 --set k_max=16 --set lr=0.0003 --set seed=1")
            && args.ends_with(&format!(
                "--out {} --resume-in-out",
                dir.join("sweep/task_003").display()
            )),
        "{args}"
    );
    let script = slurm_script(&grid, Path::new("/opt/icrl")).unwrap();
    for want in [
        "#SBATCH --array=0-3",
        "#SBATCH --cpus-per-task=1",
        "#SBATCH --partition=cpu",
        "#SBATCH --account=proj",
        "#SBATCH --requeue",
        "#SBATCH --signal=B:USR1@300",
        // 600 updates at 1.3/s, x1.5, + 10 minutes.
        "#SBATCH --time=00:21:32",
        "/opt/icrl \"${args[@]}\" &",
    ] {
        assert!(script.contains(want), "{want} missing from\n{script}");
    }
    // A bad setting fails when the grid is read, not on the cluster.
    let path = grid_file(
        &dir,
        "env = \"darkroom\"\nseeds = [0]\nout = \"s\"\n[grid]\nno_such_key = [1]\n",
    );
    let e = SweepGrid::load(&path).unwrap_err().to_string();
    assert!(e.contains("no_such_key"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_requeued_task_resumes_its_own_run() {
    let dir = std::env::temp_dir().join(format!("icrl-sweep-requeue-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = dir.join("task_000");
    let sets: Vec<String> = ["total_updates=2", "checkpoint_every=1", "seed=3"]
        .map(String::from)
        .to_vec();
    assert_eq!(
        run_in_out(&out, "darkroom", "eppo", &sets).unwrap(),
        InOut::Start
    );
    let first = crate::cli::pretrain::eppo("darkroom", "quick", None, &sets, &out).unwrap();
    assert_eq!(
        run_in_out(&out, "darkroom", "eppo", &sets).unwrap(),
        InOut::Finished {
            run: first.run_dir.clone(),
            updates: 2
        }
    );
    // Requeued with a longer run asked for: the same folder continues.
    let longer: Vec<String> = ["total_updates=3", "checkpoint_every=1", "seed=3"]
        .map(String::from)
        .to_vec();
    let InOut::Resume(run) = run_in_out(&out, "darkroom", "eppo", &longer).unwrap() else {
        panic!("expected to resume");
    };
    assert_eq!(run, first.run_dir);
    let again = crate::cli::pretrain::eppo("darkroom", "quick", Some(&run), &longer, &out).unwrap();
    assert_eq!((again.run_dir, again.updates), (first.run_dir, 3));
    assert_eq!(
        std::fs::read_dir(&out).unwrap().count(),
        1,
        "one run folder"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Trial 3, weak: an AD grid was always refused (`no preset
/// "ad-darkroom-quick"`: presets were looked up under EPPO's names
/// only). It resolves AD's presets and settings, refuses an EPPO-only
/// key, and its script passes the dataset to every task, with AD's
/// update count, measured speed and memory estimate.
#[test]
fn an_ad_grid_resolves_ad_presets_and_emits_its_script() {
    let dir = std::env::temp_dir().join(format!("icrl-sweep-ad-{}", std::process::id()));
    let base = "env = \"darkroom\"\nmethod = \"ad\"\ndataset = \"data/h.h5\"\nout = \"runs\"\n";
    let grid = SweepGrid::load(&grid_file(
        &dir,
        &format!(
            "{base}seeds = [0, 1]\n[set]\nupdates = 300\n[grid]\nlearning_rate = [1e-3, 3e-4]\n"
        ),
    ))
    .unwrap();
    assert_eq!(grid.tasks().len(), 4);
    let script = slurm_script(&grid, Path::new("/opt/icrl")).unwrap();
    let dataset = format!("--dataset {}", dir.join("data/h.h5").display());
    for want in [
        "#SBATCH --array=0-3",
        "--method ad --preset quick",
        dataset.as_str(),
        "--set 'updates=300' --set 'learning_rate=0.0003' --set 'seed=1'",
        // 300 updates at 0.75/s, x1.5, + 10 minutes.
        "#SBATCH --time=00:20:00",
        // torch_threads = 0 in the preset: one per core.
        "#SBATCH --cpus-per-task=8",
    ] {
        assert!(script.contains(want), "{want} missing from\n{script}");
    }
    let mem = script
        .lines()
        .find_map(|l| l.strip_prefix("#SBATCH --mem="))
        .and_then(|m| m.strip_suffix('G'))
        .and_then(|m| m.parse::<u64>().ok())
        .unwrap_or_else(|| panic!("no --mem in\n{script}"));
    assert!((2..=64).contains(&mem), "{mem}G");
    // AD's settings are checked as AD checks them.
    for (text, want) in [
        ("[set]\ntotal_updates = 5\n", "total_updates"),
        ("[grid]\nlearning_rate = [2.0]\n", "learning_rate = 2"),
    ] {
        let err = SweepGrid::load(&grid_file(&dir, &format!("{base}seeds = [0]\n{text}")))
            .unwrap_err()
            .to_string();
        assert!(err.contains(want), "{want}: {err}");
    }
    let err = SweepGrid::load(&grid_file(
        &dir,
        &format!("{base}seeds = [0]\npreset = \"table1\"\n"),
    ))
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("ad-darkroom-table2") && !err.contains("eppo-"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// A grid file's texts reach the generated script only when they hold no
/// control character: a newline in any Slurm option, the output folder,
/// a setting or the icrl path would put a command on a line of its own,
/// and a NUL cannot be quoted. Each is refused by its key, and nothing is
/// written.
#[test]
fn no_text_of_a_grid_file_can_add_a_line_to_the_script() {
    let dir = std::env::temp_dir().join(format!("icrl-sweep-inject-{}", std::process::id()));
    let base = "env = \"darkroom\"\nseeds = [0]\n[set]\ntotal_updates = 600\n";
    let cases = [
        (
            "slurm.partition",
            format!("{base}[slurm]\npartition = \"cpu\\ntouch FILE\"\n"),
        ),
        (
            "slurm.account",
            format!("{base}[slurm]\naccount = \"a\\ntouch FILE\"\n"),
        ),
        (
            "slurm.time",
            format!("{base}[slurm]\ntime = \"01:00:00\\ntouch FILE\"\n"),
        ),
        (
            "slurm.extra[0]",
            format!("{base}[slurm]\nextra = [\"--qos=x\\ntouch FILE\"]\n"),
        ),
        (
            "slurm.icrl",
            format!("{base}[slurm]\nicrl = \"/bin/icrl\\u0000$(touch FILE)\"\n"),
        ),
        (
            "grid.lr",
            "env = \"darkroom\"\nseeds = [0]\n[grid]\nlr = [\"1e-4\\nx\"]\n".into(),
        ),
    ];
    for (key, text) in cases {
        let text = format!("out = \"runs\"\n{text}");
        let err = SweepGrid::load(&grid_file(&dir, &text))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains(key) && err.contains("control character"),
            "{key}: {err}"
        );
    }
    let out = "env = \"darkroom\"\nseeds = [0]\nout = \"runs\\ntouch FILE\\n#\"\n";
    let err = SweepGrid::load(&grid_file(&dir, out))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("out = ") && err.contains("control character"),
        "{err}"
    );
    // The icrl binary named on the command line passes the same check.
    let grid = SweepGrid::load(&grid_file(
        &dir,
        "env = \"darkroom\"\nseeds = [0]\nout = \"runs\"\n[slurm]\ntime = \"01:00:00\"\n",
    ))
    .unwrap();
    let err = slurm_script(&grid, Path::new("/bin/icrl\n touch FILE"))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("icrl binary") && err.contains("control character"),
        "{err}"
    );
    assert!(!dir.join("runs").join("sweep.sbatch").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

/// Numbers and formats that gave silently wrong scripts are refused with
/// their bound: a speed that wraps the time limit, no CPU, a time or
/// memory Slurm cannot read, a seed given twice or in [grid] beside
/// `seeds`, an array past Slurm's size; `mem` is written as given.
#[test]
fn slurm_settings_out_of_bounds_are_refused_and_mem_is_honoured() {
    let dir = std::env::temp_dir().join(format!("icrl-sweep-bounds-{}", std::process::id()));
    let base = "env = \"darkroom\"\nout = \"runs\"\n";
    let refused = |text: &str, key: &str| {
        let err = SweepGrid::load(&grid_file(&dir, &format!("{base}{text}")))
            .unwrap_err()
            .to_string();
        assert!(err.contains(key), "{key}: {err}");
    };
    for rate in ["0", "1e-300", "-1", "nan", "inf"] {
        refused(
            &format!("seeds = [0]\n[slurm]\nupdates_per_second = {rate}\n"),
            "updates_per_second",
        );
    }
    // A number far from 1 in exponent form, not 300 zeros (the hand rerun).
    refused(
        "seeds = [0]\n[slurm]\nupdates_per_second = 1e-300\n",
        "updates_per_second = 1e-300: must be at least 1.157e-5 (one update a day",
    );
    refused("seeds = [0]\n[slurm]\ncpus_per_task = 0\n", "cpus_per_task");
    refused("seeds = [0]\n[slurm]\ntime = \"garbage\"\n", "slurm.time");
    refused("seeds = [0]\n[slurm]\nmem = \"lots\"\n", "slurm.mem");
    refused("seeds = [0, 0]\n", "repeats a seed");
    refused("seeds = [0]\n[grid]\nseed = [1, 2]\n", "grid.seed");
    refused("seeds = [0]\n[set]\nseed = 3\n", "set.seed");
    let big: String = (0..10)
        .map(|k| format!("k{k} = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]\n"))
        .collect();
    refused(&format!("seeds = [0]\n[grid]\n{big}"), "at most 1000");
    for time in ["30", "30:00", "01:00:00", "2-12", "2-12:30", "2-12:30:00"] {
        assert!(slurm_time(time), "{time}");
    }
    let grid = SweepGrid::load(&grid_file(
        &dir,
        &format!("{base}seeds = [0]\n[slurm]\nmem = \"64G\"\ntime = \"01:00:00\"\n"),
    ))
    .unwrap();
    let script = slurm_script(&grid, Path::new("/bin/icrl")).unwrap();
    assert!(script.contains("#SBATCH --mem=64G\n"), "{script}");
    let _ = std::fs::remove_dir_all(&dir);
}
