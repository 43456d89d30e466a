#!/usr/bin/env bash
# Where deadline misses come from (issue 11): one `fastemu hil` run under the kernel's
# ftrace (scheduler switches, timer starts and expiries, interrupts), then
# benches/miss_trace.py attributes every late wake-up of the SCHED_FIFO loop threads to
# its cause: the hypervisor not running the virtual CPU, another of fastemu's threads,
# a kernel thread, an interrupt. Needs root and tracefs; the trace costs a few percent of
# CPU and ~25 MB per 10 s.
#
#   benches/miss_trace.sh [DURATION_S] [OUT_DIR] [CONFIG]
#   (default: 60 s, out/miss-trace, configs/hil-durability.toml)
#
# Figures only, never pass/fail. Leaves tracing off and its buffer empty.
set -euo pipefail
cd "$(dirname "$0")/.."
DURATION=${1:-60}
OUT=${2:-out/miss-trace}
CONFIG=${3:-configs/hil-durability.toml}
EXE=target/release/fastemu
T=/sys/kernel/tracing
[ -x "$EXE" ] || { echo "build first: cargo build --release" >&2; exit 1; }
[ -d "$T/events" ] || mount -t tracefs nodev "$T" 2>/dev/null || {
  echo "miss_trace: no tracefs at $T (needs root: mount -t tracefs nodev $T)" >&2; exit 1; }
[ -w "$T/tracing_on" ] || { echo "miss_trace: $T is not writable (run as root)" >&2; exit 1; }
rm -rf "$OUT"; mkdir -p "$OUT"
restore() { echo 0 > "$T/tracing_on"; echo 0 > "$T/options/record-tgid"; echo local > "$T/trace_clock"; echo > "$T/set_event"; echo > "$T/trace"; echo 1408 > "$T/buffer_size_kb"; }
trap restore EXIT
echo 0 > "$T/tracing_on"; echo > "$T/trace"
echo mono > "$T/trace_clock"
echo 1 > "$T/options/record-tgid"
echo $(( 40000 + DURATION * 2500 )) > "$T/buffer_size_kb"
: > "$T/set_event"
for e in sched:sched_switch timer:hrtimer_start timer:hrtimer_expire_entry \
         irq_vectors:local_timer_entry irq_vectors:call_function_single_entry \
         irq_vectors:reschedule_entry irq:irq_handler_entry irq:softirq_entry \
         workqueue:workqueue_execute_start; do
  echo "$e" >> "$T/set_event"
done
steal() { awk '/^cpu[0-9]/{printf "%s=%s ", $1, $9}' /proc/stat; }
echo "steal before (1/100 s per CPU): $(steal)" > "$OUT/steal.txt"
echo 1 > "$T/tracing_on"
"$EXE" hil --config "$CONFIG" --duration-s "$DURATION" --json --out "$OUT/report" \
    > "$OUT/summary.json" 2> "$OUT/hil.err" || echo "miss_trace: hil exited with $?" >&2
echo 0 > "$T/tracing_on"
echo "steal after  (1/100 s per CPU): $(steal)" >> "$OUT/steal.txt"
for c in "$T"/per_cpu/cpu*; do
  lost=$(awk '/^overrun/{print $2}' "$c/stats")
  [ "$lost" = 0 ] || echo "miss_trace: warning: $(basename "$c") lost $lost events (buffer too small)" >&2
done
cat "$T/trace" > "$OUT/trace.txt"
python3 - "$OUT/summary.json" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
print(f"hil: {s['steps']} steps, emulator deadline misses {s['deadline_misses']} "
      f"({s['deadline_misses'] / max(s['steps'], 1):.1e}), rig {s.get('deadline_misses_rig')}, "
      f"stalls {(s.get('stalls') or {}).get('count')}, clean {s.get('clean')}")
PY
cat "$OUT/steal.txt"
python3 benches/miss_trace.py "$OUT/trace.txt" | tee "$OUT/attribution.txt"
