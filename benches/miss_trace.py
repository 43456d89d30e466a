#!/usr/bin/env python3
"""Where a run's late wake-ups come from: reads an ftrace text trace taken during a
`fastemu hil` run (benches/miss_trace.sh takes it) and attributes every late wake-up of
the SCHED_FIFO loop threads to its cause.

For each sleep of a loop thread the trace has the intended wake time (the
`hrtimer_start` of its `clock_nanosleep`: the deadline less the spin), the time the timer
interrupt actually ran (`hrtimer_expire_entry`) and the time the thread got the CPU back
(`sched_switch`). The lateness of a wake-up splits into:

  timer late   expire - intended. The CPU did not take its timer interrupt in time. If
               the CPU was idle then ("idle: vCPU not woken"), only the hypervisor can
               have held it: an idle guest CPU takes a due interrupt at once unless its
               virtual CPU is not running. If a thread was on the CPU ("busy: <comm>"),
               either the hypervisor preempted the virtual CPU or that thread ran with
               interrupts off.
  dispatch     switch-in - expire, split by what ran on the CPU meanwhile: another loop
               thread of the same priority, a kernel thread that the kernel's preemption
               model let finish (PREEMPT_NONE), an interrupt, or nothing at all for over
               50 us ("silent": the virtual CPU was not running).

A loop thread that is preempted while it spins (switched out runnable) is counted the
same way from its switch-out. Only wake-ups later than --late-us are counted.

usage: miss_trace.py TRACE [--late-us 100] [--json]
"""

import argparse
import bisect
import collections
import json
import re
import sys

LINE = re.compile(r"^\s*(.+?)-(\d+)\s+(?:\(\s*([\d-]+)\)\s+)?\[(\d+)\]\s+\S+\s+([\d.]+): (\w+): (.*)$")
# A writer thread names its process (`<process>-records`, cut to 15 characters).
WRITER = re.compile(r"^(rig|emulator|controller|link)-rec")
SWITCH = re.compile(
    r"prev_comm=(.*) prev_pid=(\d+) prev_prio=(\d+) prev_state=(\S+) ==> "
    r"next_comm=(.*) next_pid=(\d+) next_prio=(\d+)"
)
HRSTART = re.compile(r"hrtimer=(\S+) function=(\S+) expires=\d+ softexpires=(\d+)")
HREXPIRE = re.compile(r"hrtimer=(\S+) function=(\S+) now=(\d+)")
SILENT_S = 50e-6
KERNEL_RT = ("migration", "watchdog", "irq/", "rcu", "idle_inject", "ksoftirqd", "kworker")
KTHREAD = re.compile(
    r"^(kworker|kdamond|ksoftirqd|rcu|migration|kcompactd|kswapd|khugepaged|jbd2|kthreadd|"
    r"cpuhp|idle_inject|watchdog|irq/|kauditd|oom_reaper|writeback)"
)
OWN = re.compile(r"^(fastemu|bench_rig|example_rig|(rig|emulator|controller|link)-rec)")


def parse(path):
    """Per-CPU event lists and the loop threads (SCHED_FIFO: kernel prio < 100)."""
    per_cpu = collections.defaultdict(list)  # cpu -> [(t, kind, data)]
    names = {}
    loop = set()
    tgids, process_of = {}, {}
    with open(path, errors="replace") as f:
        for line in f:
            m = LINE.match(line)
            if not m:
                continue
            comm, pid, tgid, cpu, t, kind, rest = m.groups()
            cpu, t, pid = int(cpu), float(t), int(pid)
            if tgid and tgid.isdigit():
                tgids[pid] = int(tgid)
                w = WRITER.match(comm)
                if w:
                    process_of[int(tgid)] = w.group(1)
            data = None
            if kind == "sched_switch":
                s = SWITCH.match(rest)
                if not s:
                    continue
                data = (int(s.group(2)), s.group(4), s.group(5), int(s.group(6)))
                names[int(s.group(2))] = s.group(1)
                names[int(s.group(6))] = s.group(5)
                for comm_, pid_, prio_ in ((s.group(1), s.group(2), s.group(3)),
                                           (s.group(5), s.group(6), s.group(7))):
                    if int(prio_) < 100 and not comm_.startswith(KERNEL_RT):
                        loop.add(int(pid_))
            elif kind == "hrtimer_start":
                h = HRSTART.search(rest)
                if not h or h.group(2) != "hrtimer_wakeup":
                    continue
                data = (h.group(1), int(h.group(3)) / 1e9, pid)
            elif kind == "hrtimer_expire_entry":
                h = HREXPIRE.search(rest)
                if not h:
                    continue
                data = (h.group(1),)
            else:
                data = rest[:60]
            per_cpu[cpu].append((t, kind, data))
    for pid in loop:
        process = process_of.get(tgids.get(pid))
        if process:
            names[pid] = f"{process} loop"
    return per_cpu, loop, names


def task_name(data):
    """The name of the task a switch hands the CPU to: a loop thread by its process."""
    return LOOP_NAMES.get(data[3], data[2])


LOOP_NAMES = {}


def running_at(events, times, t):
    """The task on the CPU at time t (the task of the last switch before t)."""
    i = bisect.bisect_right(times, t) - 1
    while i >= 0 and events[i][1] != "sched_switch":
        i -= 1
    return task_name(events[i][2]) if i >= 0 else "?"


def attribute(events, times, t0, t1, own, out, prefix):
    """Splits [t0, t1] on one CPU by what ran there (or silence), adding seconds to out."""
    running = running_at(events, times, t0)
    i = bisect.bisect_right(times, t0)
    t = t0
    while True:
        te = events[i][0] if i < len(events) and events[i][0] < t1 else t1
        seg = te - t
        out[prefix + ("silent (vCPU not running)" if seg > SILENT_S else label(running, own))] += seg
        if te >= t1:
            return
        if events[i][1] == "sched_switch":
            running = task_name(events[i][2])
        t = te
        i += 1


def label(comm, own):
    if comm.startswith("swapper"):
        return "idle"
    if comm in own or comm.endswith(" loop"):
        return "fastemu " + comm
    return comm


def classes(causes):
    out = collections.Counter()
    for cause, seconds in causes.items():
        out[cause_class(cause)] += seconds
    return out


def cause_class(cause):
    """One of four classes for a cause line (see the module's description)."""
    what = cause.split(": ", 1)[-1].replace("timer late, CPU busy with ", "")
    if "silent" in cause or "CPU idle" in cause:
        return "hypervisor (vCPU not running or not woken)"
    if cause.startswith("timer late"):
        # A user-space thread cannot hold off an interrupt: the vCPU was not running.
        return ("kernel threads (interrupts off) or hypervisor" if KTHREAD.match(what)
                else "hypervisor (vCPU not running or not woken)")
    if what == "idle":
        return "leaving the idle state"
    if what.startswith("fastemu "):
        return "fastemu's own threads"
    if KTHREAD.match(what):
        return "kernel threads (not preempted)"
    return "other processes"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("trace")
    ap.add_argument("--late-us", type=float, default=100.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--from-s", type=float, default=0.0, help="ignore events before (trace clock, s)")
    ap.add_argument("--to-s", type=float, default=1e18, help="ignore events after (trace clock, s)")
    args = ap.parse_args()
    late_s = args.late_us * 1e-6
    per_cpu, loop, names = parse(args.trace)
    LOOP_NAMES.update({p: names[p] for p in loop if names.get(p, '').endswith(' loop')})
    times = {c: [e[0] for e in ev] for c, ev in per_cpu.items()}
    own = {n for n in names.values() if OWN.match(n)}
    merged = sorted(
        (t, cpu, kind, data) for cpu, ev in per_cpu.items() for (t, kind, data) in ev
        if args.from_s <= t <= args.to_s
    )
    result = {}
    for pid in sorted(loop):
        causes = collections.Counter()
        worst = []
        pending = {}  # hrtimer -> (intended wake, cpu)
        fired = None  # (intended, expire time, cpu) of the timer that woke the thread
        out_runnable = None  # (t, cpu) of a switch-out while runnable
        for t, cpu, kind, data in merged:
            if kind == "hrtimer_start" and data[2] == pid:
                pending[data[0]] = (data[1], cpu)
            elif kind == "hrtimer_expire_entry" and data[0] in pending:
                intended, _ = pending.pop(data[0])
                fired = (intended, t, cpu)
            elif kind == "sched_switch":
                prev, state, _, nxt = data
                if prev == pid:
                    out_runnable = (t, cpu) if not state.startswith(("S", "D", "I")) else None
                if nxt != pid:
                    continue
                ev, tl = per_cpu[cpu], times[cpu]
                if fired is not None:
                    intended, expire, tcpu = fired
                    if t - intended > late_s:
                        worst.append((t - intended, t))
                        if expire > intended:
                            who = running_at(per_cpu[tcpu], times[tcpu], intended)
                            key = ("timer late, CPU idle (vCPU not woken)" if who.startswith("swapper")
                                   else "timer late, CPU busy with " + label(who, own))
                            causes[key] += expire - intended
                        attribute(ev, tl, max(expire, intended), t, own, causes, "dispatch: ")
                elif out_runnable is not None and t - out_runnable[0] > late_s:
                    worst.append((t - out_runnable[0], t))
                    attribute(ev, tl, out_runnable[0], t, own, causes, "preempted: ")
                fired = None
                out_runnable = None
        lateness = sum(w for w, _ in worst)
        worst.sort(reverse=True)
        result[f"{names.get(pid, '?')}[{pid}]"] = {
            "late_wakeups": len(worst),
            "lateness_ms": round(lateness * 1e3, 3),
            "causes_ms": {k: round(v * 1e3, 3) for k, v in causes.most_common()},
            "classes_ms": {k: round(v * 1e3, 3) for k, v in classes(causes).most_common()},
            "worst_ms": [round(w * 1e3, 3) for w, _ in worst[:5]],
            "worst_at_s": [round(t, 6) for _, t in worst[:5]],
        }
    if args.json:
        json.dump(result, sys.stdout, indent=2)
        print()
        return
    for thread, r in result.items():
        print(f"{thread}: {r['late_wakeups']} wake-ups later than {args.late_us:.0f} us, "
              f"{r['lateness_ms']:.1f} ms late in all; worst {r['worst_ms']} ms")
        for cls, ms in r["classes_ms"].items():
            share = 100 * ms / r["lateness_ms"] if r["lateness_ms"] else 0
            print(f"  {ms:9.2f} ms {share:5.1f} %  {cls}")
            for cause, cms in r["causes_ms"].items():
                if cause_class(cause) == cls and cms >= 0.01:
                    print(f"      {cms:9.2f} ms  {cause}")


if __name__ == "__main__":
    main()
