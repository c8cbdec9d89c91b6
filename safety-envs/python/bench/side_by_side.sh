#!/usr/bin/env bash
# Side-by-side benchmark of our Python environments against Safety-Gymnasium
# (issue 53), in one run, as ratios. Run by hand from anywhere in the repository:
#
#     bash safety-envs/python/bench/side_by_side.sh
#
# About 8 minutes on 2 cores once built (most of it Safety-Gymnasium's resets);
# the table goes to stdout and to target/side-by-side/table.md, the raw figures
# to target/side-by-side/ (results.jsonl, rust-*.log, workers.log). Nothing here
# is used by CI or the tests.
#
# What it makes itself, from a fresh clone:
# 1. target/python-venv, the Python package's test environment (created by
#    `cargo xtask setup` when it is missing), with our package built into it in
#    release: `maturin develop --release` from safety-envs/python, the way
#    `cargo xtask test` builds it (VIRTUAL_ENV and PATH pointing at that venv;
#    `cargo xtask test` later rebuilds it in the dev profile).
# 2. target/safety-gymnasium-venv, its own venv with safety-gymnasium 1.0.0 from
#    PyPI, so its pins (gymnasium 0.28.1, mujoco 2.3.3, ...) never touch the
#    test venv. Those pins need Python 3.10: pygame==2.1.0 has no wheel for
#    3.11 (it fails to build from source without SDL), and on Python 3.11
#    safety_gymnasium does not even import (its asset dataclasses have
#    `np.ndarray` defaults, which 3.11 refuses: "mutable default ... use
#    default_factory"). So:
#    - with a Python 3.10 (SG_PYTHON, else python3.10 on PATH, else pyenv's
#      3.10.x), `pip install safety-gymnasium==1.0.0` installs the pins as they
#      are (pygame 2.1.0, numpy 1.23.5) - the default on the development machine;
#    - without one, on python3 (3.11+), the pins except pygame are installed
#      (`gymnasium==0.28.1 gymnasium-robotics==1.2.2 mujoco==2.3.3 numpy<2
#      pygame>=2.1.3 xmltodict pyyaml imageio`), then
#      `pip install --no-deps safety-gymnasium==1.0.0`; and side_by_side.py
#      turns those ndarray defaults into default_factory copies at import
#      (pygame is only used for human rendering, never here).
#
# What it measures, all in this one run (3 rounds; in each, the Rust bench and
# then every Python measurement in turn, so load changes hit all of them):
# - agent steps/s from Python in the paper's episode shape: episodes of 75
#   agent steps with random actions, a reset between episodes (at least 20
#   episodes and 3 s per measurement); ours `gymnasium.make(
#   "SafeDarkMujocoPoint-v0")` / `...Car-v0` (50 physics steps per agent step,
#   the default), Safety-Gymnasium `SafetyPointGoal1-v0` / `SafetyCarGoal1-v0`
#   with all lidar off and 5 `env.step` calls (10 physics steps each) with the
#   same action per agent step, time limit 375 of its steps;
# - the same with steps only (one long episode, no resets);
# - our Rust rates for the same shapes from the Rust bench
#   (safety-envs/benches/envs.rs: ENVS_BENCH_ONLY=paper, and =raw for stepping);
# and reports medians of the 3 rounds and the ratios ours/Safety-Gymnasium and
# Rust/Python.
#
# Knobs for a smoke run: SIDE_BY_SIDE_REPS (3), SIDE_BY_SIDE_SECONDS (3),
# SIDE_BY_SIDE_EPISODES (20).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)"
cd "$ROOT"
BENCH="$ROOT/safety-envs/python/bench/side_by_side.py"
VENV="$ROOT/target/python-venv"
SG_VENV="${SG_VENV:-$ROOT/target/safety-gymnasium-venv}"
OUT="$ROOT/target/side-by-side"
REPS="${SIDE_BY_SIDE_REPS:-3}"
SECONDS_MIN="${SIDE_BY_SIDE_SECONDS:-3}"
EPISODES_MIN="${SIDE_BY_SIDE_EPISODES:-20}"
SG_VERSION=1.0.0

say() { printf '\nside_by_side: %s\n' "$*"; }

# 1. Our package, in release, in the test venv.
if [[ ! -x "$VENV/bin/maturin" || ! -x "$VENV/bin/python" ]]; then
    say "target/python-venv missing: cargo xtask setup"
    cargo xtask setup
fi
say "maturin develop --release (safety-envs/python) into target/python-venv"
(
    cd safety-envs/python
    VIRTUAL_ENV="$VENV" PATH="$VENV/bin:$PATH" "$VENV/bin/maturin" develop --release --quiet
)

# 2. Safety-Gymnasium in its own venv.
find_sg_python() {
    if [[ -n "${SG_PYTHON:-}" ]]; then
        echo "$SG_PYTHON"
        return
    fi
    # A pyenv shim is on PATH even where its version is not selected: try each.
    local root candidate
    root="$(pyenv root 2>/dev/null || echo "$HOME/.pyenv")"
    for candidate in python3.10 "$root"/versions/3.10*/bin/python3.10; do
        if "$candidate" -c 'import venv, ensurepip' >/dev/null 2>&1; then
            command -v "$candidate"
            return
        fi
    done
    echo python3
}
sg_ok() { [[ -x "$SG_VENV/bin/python" ]] && "$SG_VENV/bin/python" "$BENCH" check >/dev/null 2>&1; }
if sg_ok; then
    say "Safety-Gymnasium venv present ($SG_VENV)"
else
    SG_PY="$(find_sg_python)"
    SG_MINOR="$("$SG_PY" -c 'import sys; print(sys.version_info[1])')"
    say "creating $SG_VENV with $SG_PY (Python 3.$SG_MINOR)"
    rm -rf "$SG_VENV"
    "$SG_PY" -m venv "$SG_VENV"
    PIP=("$SG_VENV/bin/python" -m pip install --quiet --disable-pip-version-check)
    if ((SG_MINOR <= 10)); then
        "${PIP[@]}" "safety-gymnasium==$SG_VERSION"
    else
        say "Python 3.$SG_MINOR: safety-gymnasium's pins without pygame==2.1.0, then it with --no-deps"
        "${PIP[@]}" "gymnasium==0.28.1" "gymnasium-robotics==1.2.2" "mujoco==2.3.3" "numpy<2" \
            "pygame>=2.1.3" "xmltodict>=0.13.0" "pyyaml>=6.0" "imageio>=2.27.0"
        "${PIP[@]}" --no-deps "safety-gymnasium==$SG_VERSION"
    fi
fi
"$SG_VENV/bin/python" "$BENCH" check 2>/dev/null

# 3. The Rust bench, built before anything is timed.
say "cargo bench -p safety-envs --bench envs --no-run"
cargo bench --quiet -p safety-envs --bench envs --no-run

# 4. The measurements.
mkdir -p "$OUT"
rm -f "$OUT"/results.jsonl "$OUT"/rust-*.log "$OUT"/workers.log
LOAD_START="$(cut -d' ' -f1-3 /proc/loadavg)"
STARTED="$(date -u '+%Y-%m-%d %H:%M UTC')"
T0=$SECONDS
for rep in $(seq 1 "$REPS"); do
    for group in paper raw; do
        say "round $rep/$REPS: Rust bench ($group)"
        ENVS_BENCH_ONLY=$group cargo bench --quiet -p safety-envs --bench envs >"$OUT/rust-$group-$rep.log"
        grep -iE '^\| (point|car):' "$OUT/rust-$group-$rep.log" || true
    done
    for robot in point car; do
        for mode in paper stepping; do
            for side in ours sg; do
                if [[ $side == ours ]]; then py="$VENV/bin/python"; else py="$SG_VENV/bin/python"; fi
                say "round $rep/$REPS: $side $robot $mode"
                "$py" "$BENCH" worker --side "$side" --robot "$robot" --mode "$mode" --rep "$rep" \
                    --min-episodes "$EPISODES_MIN" --min-seconds "$SECONDS_MIN" \
                    2>>"$OUT/workers.log" | tee -a "$OUT/results.jsonl"
            done
        done
    done
done
LOAD_END="$(cut -d' ' -f1-3 /proc/loadavg)"

HEADER="Side by side, $STARTED, $((SECONDS - T0)) s: $(nproc) cores ($(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ *//')), load average $LOAD_START at the start, $LOAD_END at the end. Agent steps/s (50 physics steps each), medians of $REPS rounds."
RUST_LOGS=()
for f in "$OUT"/rust-*.log; do RUST_LOGS+=(--rust-log "$f"); done
say "table ($OUT/table.md)"
"$VENV/bin/python" "$BENCH" table --results "$OUT/results.jsonl" "${RUST_LOGS[@]}" \
    --header "$HEADER" --out "$OUT/table.md"
