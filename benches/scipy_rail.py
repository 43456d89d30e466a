#!/usr/bin/env python3
"""fastemu vs SciPy on the offline rail scenario (SPEC 7: >= 100x faster at equal accuracy).

Scenario: a mass on one metre of the ERS elastomer (Li et al. 2021, Table 3), 60.21 kg
(UIC60), driven by a 55 kN step at t = 0 plus a 1 kN, 170 Hz harmonic, null initial
conditions (`--start rest`), 2 s sampled at 100 kHz (200 001 samples).

Measured, each as the median of repeated runs:
  cli      wall clock of `fastemu simulate rail` (process start, CSV read, simulate, CSV write)
  kernel   `fastemu bench rail --json`: `simulate_rail` alone, in process, no I/O
  scipy    `solve_ivp(method="DOP853", rtol=1e-8)` on the same ODE, the load linearly
           interpolated between samples as fastemu does; timed alone ("compute") and with
           reading the load CSV and writing the result CSV ("script")
and the relative RMS difference of the displacement histories.

At rtol=1e-8 the difference (~2e-5 relative RMS) is SciPy's own error: against SciPy at
rtol=1e-12 fastemu differs by ~2e-8 and SciPy at 1e-8 by ~1e-5. `--rtol 1e-11` matches
fastemu's accuracy but needs ~14 M right-hand-side calls (minutes: the load's slope
jumps at every sample), so the default compares at rtol=1e-8, which favours SciPy.

Usage: python3 benches/scipy_rail.py [--form consistent|paper] [--cli-runs 5]
       [--scipy-runs 3] [--fastemu target/release/fastemu] [--json]
Needs numpy and scipy (pip install numpy scipy) and a release build (cargo build --release).
"""

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
from scipy.integrate import solve_ivp

# Li et al. (2021) Table 3, per metre; unit length so per metre == per element.
K1_0, K2_0, C2_0, CHI, P0 = 62e6, 9.6e6, 0.7e6, 0.21, 64e3
BASE_MIN = 1e-6  # fastemu's clamp of the power-law base (model/params.rs)
MASS_KG = 60.21
STEP_N, HARMONIC_N, HARMONIC_HZ = 55e3, 1e3, 170.0


def model_toml(form):
    return (
        f'form = "{form}"\nlength_m = 1.0\nk1_0_n_per_m2 = {K1_0!r}\nk2_0_n_per_m2 = {K2_0!r}\n'
        f"c2_0_ns_per_m2 = {C2_0!r}\nchi = {CHI!r}\np0_n = {P0!r}\n"
    )


def write_load_csv(path, duration_s, rate_hz):
    n = int(round(duration_s * rate_hz)) + 1
    t = np.arange(n) / rate_hz
    f = STEP_N + HARMONIC_N * np.sin(2.0 * np.pi * HARMONIC_HZ * t)
    with open(path, "w") as out:
        out.write("t_s,force_n\n")
        # repr-exact floats so both sides read identical samples.
        out.writelines(f"{ti!r},{fi!r}\n" for ti, fi in zip(t.tolist(), f.tolist()))
    return t, f


def make_rhs(form, t0, dt, load):
    """The ODE fastemu integrates (model/oscillator.rs), state [x, v, q]."""
    a = K2_0 / C2_0
    ratio = K2_0 / K1_0
    n_last = len(load) - 1
    load = load.tolist()  # Python floats: faster than numpy scalars in a scalar RHS

    def external(t):
        s = (t - t0) / dt
        i = min(max(int(s), 0), n_last - 1)
        w = s - i
        return load[i] + (load[i + 1] - load[i]) * w

    if form == "consistent":
        # F = Fs(x) + Fm, Fs = P0 [(1 + (1-chi) k1_0 x / P0)^(1/(1-chi)) - 1],
        # dFm/dt = (k2_0/k1_0) dFs/dx v - a Fm, dFs/dx = k1_0 (1 + Fs/P0) / base.
        omc = 1.0 - CHI

        def rhs(t, y):
            x, v, q = y
            base = 1.0 + omc * K1_0 * x / P0
            if base < BASE_MIN:
                base, tangent_on = BASE_MIN, 0.0
            else:
                tangent_on = 1.0
            fs = P0 * (base ** (1.0 / omc) - 1.0)
            tangent = tangent_on * K1_0 * (1.0 + fs / P0) / base
            return [v, (external(t) - fs - q) / MASS_KG, ratio * tangent * v - a * q]

    else:
        # Paper Eq. 3 with P = F(t): dF/dt = g(F) [(k1_0+k2_0) v + a k1_0 x] - a F.
        def rhs(t, y):
            x, v, q = y
            g = max(1.0 + q / P0, BASE_MIN) ** CHI
            return [v, (external(t) - q) / MASS_KG, g * ((K1_0 + K2_0) * v + a * K1_0 * x) - a * q]

    return rhs


def scipy_solve(form, t, load, rtol):
    dt = (t[-1] - t[0]) / (len(t) - 1)
    rhs = make_rhs(form, t[0], dt, load)
    # Scales: x ~ 1e-3 m, v ~ 1 m/s, q ~ 1e4 N; atol ~ 1e-3 rtol of each, so rtol rules.
    atol = [1e-3 * rtol * 1e-3, 1e-3 * rtol, 1e-3 * rtol * 1e4]
    sol = solve_ivp(rhs, (t[0], t[-1]), [0.0, 0.0, 0.0], method="DOP853",
                    t_eval=t, rtol=rtol, atol=atol)
    if not sol.success:
        raise RuntimeError(sol.message)
    return sol


def element_force(form, x, q):
    if form == "consistent":
        base = np.maximum(1.0 + (1.0 - CHI) * K1_0 * x / P0, BASE_MIN)
        return P0 * (base ** (1.0 / (1.0 - CHI)) - 1.0) + q
    return q


def median_time(fn, runs):
    times = []
    result = None
    for _ in range(runs):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), times, result


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--form", choices=["consistent", "paper"], default="consistent")
    parser.add_argument("--fastemu", default=os.path.join(
        os.path.dirname(os.path.abspath(__file__)), "..", "target", "release", "fastemu"))
    parser.add_argument("--cli-runs", type=int, default=5)
    parser.add_argument("--kernel-runs", type=int, default=9)
    parser.add_argument("--scipy-runs", type=int, default=3)
    parser.add_argument("--rtol", type=float, default=1e-8)
    parser.add_argument("--duration-s", type=float, default=2.0)
    parser.add_argument("--rate-hz", type=float, default=100e3)
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="fastemu-scipy-") as work:
        model = os.path.join(work, f"unit-{args.form}.toml")
        with open(model, "w") as out:
            out.write(model_toml(args.form))
        load_csv = os.path.join(work, "load.csv")
        out_csv = os.path.join(work, "x.csv")
        t, load = write_load_csv(load_csv, args.duration_s, args.rate_hz)

        cli = [args.fastemu, "simulate", "rail", "--model", model, "--mass-kg", repr(MASS_KG),
               "--input", load_csv, "--out", out_csv, "--start", "rest"]
        subprocess.run(cli, check=True)  # warm the page cache once
        cli_s, cli_all, _ = median_time(lambda: subprocess.run(cli, check=True), args.cli_runs)
        ours = np.loadtxt(out_csv, delimiter=",", skiprows=1)

        kernel = json.loads(subprocess.run(
            [args.fastemu, "bench", "rail", "--model", model, "--mass-kg", repr(MASS_KG),
             "--input", load_csv, "--start", "rest", "--runs", str(args.kernel_runs), "--json"],
            check=True, capture_output=True, text=True).stdout)

        def scipy_script():
            data = np.loadtxt(load_csv, delimiter=",", skiprows=1)
            sol = scipy_solve(args.form, data[:, 0], data[:, 1], args.rtol)
            x, v, q = sol.y
            np.savetxt(os.path.join(work, "x-scipy.csv"),
                       np.column_stack([sol.t, x, v, element_force(args.form, x, q)]),
                       delimiter=",", header="t_s,displacement_m,velocity_m_per_s,element_force_n",
                       comments="", fmt="%.17g")
            return sol

        script_s, script_all, sol = median_time(scipy_script, args.scipy_runs)
        compute_s, compute_all, _ = median_time(
            lambda: scipy_solve(args.form, t, load, args.rtol), args.scipy_runs)

    x_ref = sol.y[0]
    x_ours = ours[:, 1]
    diff = x_ours - x_ref
    rel_rms = math.sqrt(np.mean(diff ** 2) / np.mean(x_ref ** 2))
    dyn = x_ref - x_ref.mean()
    rel_rms_dynamic = math.sqrt(np.mean(diff ** 2) / np.mean(dyn ** 2))
    f_ours = ours[:, 3]
    f_ref = element_force(args.form, sol.y[0], sol.y[2])
    rel_rms_force = math.sqrt(np.mean((f_ours - f_ref) ** 2) / np.mean(f_ref ** 2))

    result = {
        "scenario": {"form": args.form, "length_m": 1.0, "mass_kg": MASS_KG,
                     "load": f"{STEP_N:g} N step + {HARMONIC_N:g} N at {HARMONIC_HZ:g} Hz",
                     "start": "rest", "duration_s": args.duration_s, "rate_hz": args.rate_hz,
                     "n_samples": len(t)},
        "fastemu_cli_s": cli_s, "fastemu_cli_runs_s": cli_all,
        "fastemu_kernel_s": kernel["median_s"], "fastemu_kernel": kernel,
        "scipy_script_s": script_s, "scipy_script_runs_s": script_all,
        "scipy_compute_s": compute_s, "scipy_compute_runs_s": compute_all,
        "scipy_rhs_evaluations": int(sol.nfev), "scipy_rtol": args.rtol,
        "speedup_cli_vs_script": script_s / cli_s,
        "speedup_kernel_vs_compute": compute_s / kernel["median_s"],
        "displacement_rel_rms": rel_rms,
        "displacement_rel_rms_of_dynamic_part": rel_rms_dynamic,
        "element_force_rel_rms": rel_rms_force,
        "python": sys.version.split()[0], "numpy": np.__version__,
        "scipy": __import__("scipy").__version__,
    }
    if args.json:
        print(json.dumps(result))
        return
    print(f"scenario: {result['scenario']}")
    print(f"fastemu simulate rail (CLI, incl. CSV I/O): median {cli_s:.4f} s over {args.cli_runs} runs")
    print(f"fastemu simulate_rail kernel:               median {kernel['median_s']:.5f} s "
          f"({kernel['median_ns_per_step']:.1f} ns/step, {kernel['substeps_per_step']} RK4 sub-step(s))")
    print(f"SciPy script (CSV read + solve_ivp + CSV write): median {script_s:.3f} s over {args.scipy_runs} runs")
    print(f"SciPy solve_ivp DOP853 rtol={args.rtol:g}:      median {compute_s:.3f} s "
          f"({sol.nfev} RHS evaluations)")
    print(f"speed-up CLI vs script:   {result['speedup_cli_vs_script']:.0f}x")
    print(f"speed-up kernel vs solve: {result['speedup_kernel_vs_compute']:.0f}x")
    print(f"displacement relative RMS difference: {rel_rms:.2e} "
          f"({rel_rms_dynamic:.2e} of the dynamic part); element force: {rel_rms_force:.2e}")


if __name__ == "__main__":
    main()
