#!/bin/bash
# Benchmark (not CI): the robustness grid of fr1_xyz (first 300 frames) as a Slurm job array
# on a one-node cluster made on this machine, against the same grid run locally.
#
#   scripts/slurm/local-cluster-bench.sh [SEQUENCE] [OUT]
#
# Installs slurmctld, slurmd, slurm-client and munge from the distribution's packages (apt,
# as root), writes a one-node slurm.conf (this host, its cores and memory; no cgroups, so it
# runs in a container too), starts munged, slurmctld and slurmd, then:
#   1. homing bench robustness --sequence SEQUENCE --plan-only --out OUT/plan
#   2. sbatch --array=1-N%CORES --wait scripts/slurm/robustness.sbatch
#   3. homing bench robustness --collect OUT/plan
#   4. homing bench robustness --sequence SEQUENCE --jobs CORES --out OUT/local
#   5. the two robustness.csv compared row for row (run times and output folders aside)
# and prints each step's wall time. The daemons are stopped at the end. Needs the release
# build (cargo build --release -p homing).
set -euo pipefail
cd "$(dirname "$0")/../.."
SEQ=${1:-../shared/datasets/rgbd_dataset_freiburg1_xyz_first300}
OUT=${2:-out/slurm-bench}
HOMING=$PWD/target/release/homing
[ -x "$HOMING" ] || { echo "build first: cargo build --release -p homing" >&2; exit 1; }
[ -d "$SEQ" ] || { echo "no sequence at $SEQ" >&2; exit 1; }
SUDO=""; [ "$(id -u)" = 0 ] || SUDO=sudo
now() { date +%s.%N; }
took() { python3 -c "print(f'{$(now) - $1:.1f}')"; }

t=$(now)
$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq slurmctld slurmd slurm-client munge >/dev/null
echo "install: $(took "$t") s"

# One node: this host, all its cores, 90 % of its memory.
HOST=$(hostname -s)
CORES=$(nproc)
MEM=$(awk '/MemTotal/ {print int($2 / 1024 * 0.9)}' /proc/meminfo)
$SUDO mkdir -p /etc/slurm /var/lib/slurm/slurmctld /var/lib/slurm/slurmd /var/log/slurm /run/munge
$SUDO tee /etc/slurm/slurm.conf >/dev/null <<CONF
ClusterName=homing-bench
SlurmctldHost=$HOST
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=/var/lib/slurm/slurmctld
SlurmdSpoolDir=/var/lib/slurm/slurmd
SlurmctldPidFile=/run/slurmctld.pid
SlurmdPidFile=/run/slurmd.pid
SlurmctldLogFile=/var/log/slurm/slurmctld.log
SlurmdLogFile=/var/log/slurm/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
# A one-node cluster of short tasks: start the next array task as soon as one ends (the
# defaults wait up to 3 s per scheduling pass, which doubled this benchmark's wall time).
SchedulerType=sched/builtin
SchedulerParameters=sched_min_interval=0,batch_sched_delay=0
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ReturnToService=2
NodeName=$HOST CPUs=$CORES RealMemory=$MEM State=UNKNOWN
PartitionName=bench Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
CONF
[ -f /etc/munge/munge.key ] || $SUDO mungekey --create
$SUDO chown munge:munge /etc/munge/munge.key /run/munge 2>/dev/null || true
pgrep -x munged >/dev/null || $SUDO runuser -u munge -- /usr/sbin/munged
stop() { $SUDO pkill -x slurmd || true; $SUDO pkill -x slurmctld || true; sleep 1; }
stop  # daemons left from an earlier run would keep their old configuration
$SUDO slurmctld
$SUDO slurmd
trap stop EXIT
for _ in $(seq 60); do
  sinfo -h -o %t 2>/dev/null | grep -q idle && break
  sleep 1
done
sinfo

mkdir -p "$OUT"
OUT=$(realpath "$OUT")
rm -rf "$OUT/plan" "$OUT/local"
t=$(now)
"$HOMING" -q bench robustness --sequence "$SEQ" --plan-only --out "$OUT/plan"
N=$(wc -l < "$OUT/plan/jobs.txt")
echo "plan ($N jobs, inputs prepared): $(took "$t") s"

t=$(now)
(cd "$OUT" && sbatch --wait --array=1-"$N"%"$CORES" --mem=1G --export=ALL,PLAN="$OUT/plan" \
  "$OLDPWD/scripts/slurm/robustness.sbatch")
echo "job array ($N tasks, $CORES at a time): $(took "$t") s"

t=$(now)
"$HOMING" -q bench robustness --collect "$OUT/plan" > "$OUT/collect.txt"
echo "collect: $(took "$t") s"

t=$(now)
"$HOMING" -q bench robustness --sequence "$SEQ" --jobs "$CORES" --out "$OUT/local" > "$OUT/local.txt"
echo "local run (--jobs $CORES): $(took "$t") s"

python3 - "$OUT/plan" "$OUT/local" <<'PY'
import csv, sys
def rows(out):
    with open(f"{out}/robustness.csv") as f:
        rs = list(csv.DictReader(f))
    for r in rs:
        r.pop("wall_s"); r.pop("fps")
        r["command"] = r["command"].replace(out, "OUT")
    return rs
a, b = rows(sys.argv[1]), rows(sys.argv[2])
same = sum(x == y for x, y in zip(a, b))
print(f"rows: {len(a)} collected from the job array, {len(b)} local, {same} identical")
sys.exit(0 if len(a) == len(b) and same == len(a) else 1)
PY
