#!/usr/bin/env bash
# Soak figures for the README (issue 11): one long `fastemu hil` run of the durability
# programme, each process's resident memory sampled every 10 s, then the report's
# deadline misses, stalls, transients and the record size per hour.
#
#   benches/soak.sh [DURATION_S] [OUT_DIR] [CONFIG]
#   (default: 3600 s, out/soak, configs/hil-durability.toml)
#
# Needs a release build (cargo build --release). Timings stay out of pass/fail tests:
# this prints figures; it fails only if the run itself fails.
set -euo pipefail
cd "$(dirname "$0")/.."
DURATION=${1:-3600}
OUT=${2:-out/soak}
CONFIG=${3:-configs/hil-durability.toml}
EXE=target/release/fastemu
[ -x "$EXE" ] || { echo "build first: cargo build --release" >&2; exit 1; }
rm -rf "$OUT"; mkdir -p "$OUT"
# GNU time, when installed, gives hil's peak resident memory (the report's streaming
# pass at the end included, which 10 s samples can miss).
TIME=()
[ -x /usr/bin/time ] && TIME=(/usr/bin/time -f %M -o "$OUT/hil.maxrss_kb")
"${TIME[@]}" "$EXE" hil --config "$CONFIG" --duration-s "$DURATION" --json --out "$OUT/report" \
    > "$OUT/summary.json" 2> "$OUT/hil.err" &
WRAPPER=$!
HIL=$WRAPPER
if [ ${#TIME[@]} -gt 0 ]; then
  for _ in $(seq 50); do HIL=$(pgrep -P "$WRAPPER" || true); [ -n "$HIL" ] && break; sleep 0.1; done
  HIL=${HIL:-$WRAPPER}
fi
echo "soak: $DURATION s, report in $OUT/report; memory samples in $OUT/rss.tsv" >&2
printf 't_s\tprocess\trss_kb\n' > "$OUT/rss.tsv"
START=$(date +%s)
while kill -0 "$HIL" 2>/dev/null; do
  NOW=$(( $(date +%s) - START ))
  for p in $(pgrep -P "$HIL" || true); do
    name=$(tr '\0' ' ' < "/proc/$p/cmdline" 2>/dev/null | awk '{n=$1; sub(".*/","",n); print ($2 ~ /^--/ ? n : n"-"$2)}')
    rss=$(awk '/VmRSS/{print $2}' "/proc/$p/status" 2>/dev/null || true)
    [ -n "$rss" ] && printf '%s\t%s\t%s\n' "$NOW" "$name" "$rss" >> "$OUT/rss.tsv"
  done
  rss=$(awk '/VmRSS/{print $2}' "/proc/$HIL/status" 2>/dev/null || true)
  [ -n "$rss" ] && printf '%s\thil\t%s\n' "$NOW" "$rss" >> "$OUT/rss.tsv"
  sleep 10
done
wait "$WRAPPER" || echo "soak: hil exited with $?" >&2
python3 - "$OUT" "$DURATION" <<'PY'
import json, os, sys, collections
out, duration = sys.argv[1], float(sys.argv[2])
s = json.load(open(os.path.join(out, "summary.json")))
rss = collections.defaultdict(list)
for line in open(os.path.join(out, "rss.tsv")).read().splitlines()[1:]:
    t, p, kb = line.split("\t"); rss[p].append((int(t), int(kb)))
print(f"soak: {duration:.0f} s requested, ran {s.get('programme', {}).get('programme_time_s') or 0:.0f} s of programme, exit {'clean' if s.get('clean') else 'not clean: ' + '; '.join(s.get('not_clean_because', []))}")
# Memory while the programme runs (samples up to DURATION) apart from what `hil` uses
# afterwards to build the report (a streaming pass over the records, bounded on its own).
for p, v in sorted(rss.items()):
    run = [(t, kb) for t, kb in v if t <= duration] or v[:1]
    t_first, first = next(((t, kb) for t, kb in run if t >= 60), run[0]); t_last, last = run[-1]
    after = [kb for t, kb in v if t > duration]
    report = f"; {max(after)/1024:.1f} MB while it builds the report" if after else ""
    print(f"  {p:22s} RSS at {t_first:4d} s {first/1024:6.1f} MB, at {t_last:4d} s {last/1024:6.1f} MB, change {(last-first)/1024:+.1f} MB{report}")
maxrss = os.path.join(out, "hil.maxrss_kb")
if os.path.exists(maxrss):
    print(f"  hil's peak resident memory (GNU time): {int(open(maxrss).read().split()[-1])/1024:.1f} MB")
steps = s["steps"]; misses = s["deadline_misses"]
print(f"  model steps {steps}, emulator deadline misses {misses} ({misses/max(steps,1):.1e}), cycles run by its standby thread {s.get('emulator_standby_cycles', 0)}; rig deadline misses {s.get('deadline_misses_rig')}")
st = s.get("stalls") or {}
print(f"  stalls {st.get('count')}, longest {st.get('longest_ms', 0):.1f} ms, largest transient {st.get('largest_transient_um', 0):.2f} um; largest transient overall {s.get('largest_transient_um', 0):.2f} um")
print(f"  faults {s['faults']}; displacement error {s['fidelity']['displacement_rel_rms']*100:.3f} %; cycles {s['programme']['cycles_completed']}")
size = os.path.getsize(os.path.join(out, "report", "records.mcap")) if os.path.exists(os.path.join(out, "report", "records.mcap")) else 0
run_s = s['programme']['programme_time_s'] or duration
print(f"  records.mcap {size/1e6:.1f} MB = {size/1e9*3600/run_s:.2f} GB per hour")
PY
# The records read to their end by an independent reader (Python's `mcap`, if installed):
# every message of every channel, and the time of the last.
if python3 -c "import mcap" 2>/dev/null; then
  python3 - "$OUT/report/records.mcap" <<'PY'
import collections, sys
from mcap.reader import make_reader
counts, first, last = collections.Counter(), None, None
with open(sys.argv[1], "rb") as f:
    for _schema, channel, msg in make_reader(f).iter_messages():
        counts[channel.topic] += 1
        first = msg.log_time if first is None else min(first, msg.log_time)
        last = msg.log_time if last is None else max(last, msg.log_time)
span = (last - first) / 1e9 if counts else 0.0
print(f"  records.mcap read to its end with Python mcap: {sum(counts.values())} messages over {span:.1f} s ({', '.join(f'{t} {n}' for t, n in sorted(counts.items()))})")
PY
else
  echo "  (pip install mcap to read records.mcap to its end with Python's reader)"
fi
