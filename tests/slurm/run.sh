#!/usr/bin/env bash
# A real Slurm on this machine: one node (localhost, this machine's cores),
# slurmctld + slurmd + munged, all under a temporary folder, on ports 16817-8.
# Submits what a user on a cluster would: the sbatch script of a 2-seed sweep
# of tiny SafeDarkRoom EPPO runs (`icrl sweep --emit slurm`), one of its tasks
# requeued while it trains (it must resume its own run, not restart), and a
# 2-shard dataset as a job array with the merge as a dependent job. Then
# checks that every task finished, every run folder is complete, and the
# merged file reads (icrl and h5py), and gathers the sweep's table.
#
# Usage (as root; `cargo xtask test --slurm` builds icrl and runs this):
#   tests/slurm/run.sh [--install] ICRL_BINARY
# --install: apt-get install slurm-wlm and munge when missing.
set -euo pipefail

install=0
if [ "${1:-}" = "--install" ]; then install=1; shift; fi
icrl=$(realpath "${1:?usage: run.sh [--install] ICRL_BINARY}")
started=$SECONDS
say() { printf '[slurm-test %4ds] %s\n' "$((SECONDS - started))" "$*"; }

if ! command -v slurmctld >/dev/null || ! command -v munged >/dev/null; then
  if [ "$install" = 1 ]; then
    say "installing slurm-wlm and munge (apt)"
    DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends slurm-wlm munge >/dev/null
  else
    echo "slurm-wlm and munge are not installed: pass --install (cargo xtask test --slurm does)" >&2
    exit 2
  fi
fi
say "$(slurmctld -V), $(munged -V 2>&1 | head -1)"

work=$(mktemp -d /tmp/icrl-slurm.XXXXXX)
mkdir -p "$work"/{state,spool,munge,log}
chmod 755 "$work"
cleanup() {
  for p in slurmd slurmctld munge-run/munged; do
    [ -f "$work/$p.pid" ] && kill "$(cat "$work/$p.pid")" 2>/dev/null || true
  done
}
trap cleanup EXIT

# munge: its own key (a private folder) and socket (a folder all may enter),
# run as the munge user it insists on.
mkdir -p "$work/munge-run"
chown munge: "$work/munge" "$work/munge-run"
chmod 700 "$work/munge"
chmod 755 "$work/munge-run"
runuser -u munge -- mungekey --create --keyfile="$work/munge/munge.key" 2>/dev/null \
  || dd if=/dev/urandom bs=1 count=1024 of="$work/munge/munge.key" 2>/dev/null
chown munge: "$work/munge/munge.key"
chmod 400 "$work/munge/munge.key"
runuser -u munge -- munged --key-file="$work/munge/munge.key" \
  --socket="$work/munge-run/munge.socket" --pid-file="$work/munge-run/munged.pid" \
  --log-file="$work/munge/munged.log" --seed-file="$work/munge/seed"

cpus=$(nproc)
mem_mb=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 - 1024 ))
export SLURM_CONF="$work/slurm.conf"
cat >"$SLURM_CONF" <<EOF
ClusterName=icrltest
SlurmctldHost=localhost
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
AuthInfo=socket=$work/munge-run/munge.socket
CredType=cred/munge
SlurmctldPort=16817
SlurmdPort=16818
StateSaveLocation=$work/state
SlurmdSpoolDir=$work/spool
SlurmctldPidFile=$work/slurmctld.pid
SlurmdPidFile=$work/slurmd.pid
SlurmctldLogFile=$work/log/slurmctld.log
SlurmdLogFile=$work/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/filetxt
JobCompLoc=$work/log/jobcomp.txt
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ReturnToService=2
MpiDefault=none
KillWait=60
NodeName=localhost NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=local Nodes=localhost Default=YES MaxTime=INFINITE State=UP
EOF
slurmctld
slurmd -N localhost
for _ in $(seq 60); do
  sinfo -h -o %T 2>/dev/null | grep -qE '^(idle|mixed|allocated)' && break
  sleep 1
done
say "cluster up: $(sinfo -h -o '%P %D node(s) %c cpus %T')"

# Wait until no job of ours is pending or running (at most $1 seconds).
wait_idle() {
  for _ in $(seq "$1"); do
    [ -z "$(squeue -h -o %i)" ] && return 0
    sleep 2
  done
  echo "jobs still queued after $(( $1 * 2 )) s:" >&2; squeue >&2; return 1
}

# --- the sweep: 2 seeds x 1 setting, tiny SafeDarkRoom EPPO runs ----------
sweep="$work/sweep"
mkdir -p "$sweep"
cat >"$sweep/sweep.toml" <<EOF
env = "darkroom"
seeds = [0, 1]
out = "runs"
[set]
total_updates = 40
checkpoint_every = 5
[grid]
lr = [0.0003]
[slurm]
partition = "local"
mem = "2G"
EOF
"$icrl" sweep --grid "$sweep/sweep.toml" --emit slurm
script="$sweep/runs/sweep.sbatch"
array=$(sbatch --parsable "$script")
say "sweep submitted: array job $array (2 tasks)"

# Requeue task 0 once it has a checkpoint: Slurm stops it (SIGTERM: icrl
# checkpoints and exits 130) and runs it again, and the second run must
# resume its own run folder.
for _ in $(seq 300); do
  ls -d "$sweep"/runs/task_000/*/checkpoints/step_* >/dev/null 2>&1 && break
  sleep 1
done
first_ckpt=$(ls -d "$sweep"/runs/task_000/*/checkpoints/step_* | sort -V | tail -1)
say "task 0 reached ${first_ckpt##*/}: scontrol requeue ${array}_0"
scontrol requeue "${array}_0"

# --- the dataset: 2 shards as an array, the merge after both --------------
data="$work/data"
mkdir -p "$data"
shards=$(sbatch --parsable --array=0-1 --mem=1G --output="$data/shard_%a.out" --wrap \
  "exec '$icrl' dataset --env darkroom --source noisy-optimal --tasks 2 --steps 400 --threads 1 \
   --shard \$SLURM_ARRAY_TASK_ID/2 --out '$data'/shard_\$SLURM_ARRAY_TASK_ID.h5")
merge=$(sbatch --parsable --dependency=afterok:"$shards" --mem=1G --output="$data/merge.out" --wrap \
  "exec '$icrl' dataset merge --out '$data/all.h5' '$data/shard_0.h5' '$data/shard_1.h5'")
say "dataset submitted: shards $shards, merge $merge (after both)"

wait_idle 600
say "all jobs left the queue"

# --- checks -----------------------------------------------------------------
fail() { echo "FAILED: $*" >&2; exit 1; }
echo "--- job records (jobcomp), in order: job, array task, name, state, exit code, start, end"
awk '{ delete f; for (i = 1; i <= NF; i++) { split($i, kv, "="); f[kv[1]] = substr($i, length(kv[1]) + 2) }
       print f["JobId"], f["ArrayJobId"] "_" f["ArrayTaskId"], f["Name"], f["JobState"],
             f["ExitCode"], f["StartTime"], f["EndTime"] }' "$work/log/jobcomp.txt"
# Every job's last record must be COMPLETED (the requeued task also has a
# record of its requeue): 2 sweep tasks, 2 shards, the merge.
final=$(awk '{ for (i = 1; i <= NF; i++) { split($i, kv, "=");
                 if (kv[1] == "JobId") id = kv[2]; if (kv[1] == "JobState") st = kv[2] }
               last[id] = st }
             END { for (id in last) print id, last[id] }' "$work/log/jobcomp.txt")
[ "$(grep -c ' COMPLETED$' <<<"$final")" = 5 ] || fail "not all 5 jobs completed: $final"

for t in 0 1; do
  dir="$sweep/runs/task_00$t"
  runs=$(ls -d "$dir"/darkroom__eppo__* | wc -l)
  [ "$runs" = 1 ] || fail "task $t has $runs run folders (a requeue restarted instead of resuming)"
  run=$(ls -d "$dir"/darkroom__eppo__*)
  [ -d "$run/checkpoints/step_40" ] || fail "task $t: no final checkpoint in $run"
  for f in config.toml metrics.jsonl learning_curve.png; do
    [ -s "$run/$f" ] || fail "task $t: $run/$f missing"
  done
  say "task $t complete: ${run#"$work"/} ($(ls "$run/checkpoints" | tr '\n' ' '))"
done
log0=$(ls "$sweep"/runs/logs/"${array}"_0.out)
grep -q "^stopped after update" "$log0" && grep -q -- "--resume-in-out: resuming" "$log0" \
  || fail "requeued task 0 did not stop with a checkpoint and resume: $(cat "$log0")"
say "requeued task 0: $(grep -m1 '^stopped after update' "$log0" | sed "s|$work/||")"
say "requeued task 0: $(grep -m1 -- '--resume-in-out: resuming' "$log0" | sed "s|$work/||")"

"$icrl" plot-histories "$data/all.h5" --out "$data/all_histories" >/dev/null
python3 - "$data/all.h5" <<'EOF'
import sys, h5py
f = h5py.File(sys.argv[1], "r")
assert f["rewards"].is_virtual and len(f["rewards"].virtual_sources()) == 2
assert int(f.attrs["grid_histories"]) == 6 and f["cost_limit"].shape == (6,)
assert list(f["history_id"][:]) == sorted(f["history_id"][:]) and f["history_id"][-1] == 5
print(f"h5py reads the merged file: {f['rewards'].shape[0]} steps, 6 histories over 2 shards")
EOF
say "merged dataset reads (icrl plot-histories and h5py)"

"$icrl" sweep --grid "$sweep/sweep.toml" --gather --tasks 2 --episodes 4 --n-budgets 2 --threads "$cpus"
say "passed"
