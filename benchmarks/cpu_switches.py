"""Same verdicts on any CPU: the tracking, grounding and calibration tests under the switches that change which
machine code the libraries run, and on one and two cores.

A test that passes on one machine and fails on another (issue 59: the occluded-box test failed every time on a
2-core AMD EPYC with AVX-512 and passed on Intel) depends on something the machine chooses: the SIMD kernels numpy,
OpenCV, torch, numba and llvmpipe dispatch to, the thread count, the order of a parallel sum. This script runs the
same tests under each configuration and compares the verdicts test by test:

    default      as `make test` runs them (all cores, every instruction set the CPU has)
    no-avx512    AVX-512 kernels off in numpy, OpenCV, torch, numba and llvmpipe (Mesa's software renderer)
    one-core     the process pinned to one core (`taskset`), one thread in OpenMP and BLAS
    two-threads  OpenMP and BLAS held to two threads

Each configuration first prints what the libraries report they run (so a switch that is silently ignored shows),
then the test counts; any test whose verdict differs between configurations, or that fails, is listed, and the
exit code is 1.

    .venv/bin/python benchmarks/cpu_switches.py [--tests tests/grounder/tracking/test_pipeline.py ...] [--configs
    default,one-core]

Figures: docs/test_timing.md.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_TESTS = (
    "tests/grounder/tracking/test_pipeline.py",
    "tests/grounder/grounding/test_pipeline.py",
    "tests/grounder/calibration/test_fit.py",
)

NO_AVX512 = {
    # numpy >= 2.4 groups AVX-512 as X86_V4 plus two extensions; it refuses names it does not dispatch
    "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR",
    "OPENCV_CPU_DISABLE": "AVX512-SKX",  # OpenCV's own name (with a hyphen); AVX512_SKX is "unknown" to it
    "ATEN_CPU_CAPABILITY": "avx2",
    "NUMBA_CPU_NAME": "haswell",
    "LP_NATIVE_VECTOR_WIDTH": "256",
}
ONE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
TWO_THREADS = {"OMP_NUM_THREADS": "2", "OPENBLAS_NUM_THREADS": "2", "MKL_NUM_THREADS": "2", "NUMBA_NUM_THREADS": "2"}
CONFIGS: dict[str, tuple[dict[str, str], list[str]]] = {
    "default": ({}, []),
    "no-avx512": (NO_AVX512, []),
    "one-core": (ONE_THREAD, ["taskset", "-c", "0"]),
    "two-threads": (TWO_THREADS, []),
}

PROBE = """
import os, numpy, cv2, torch, numba
simd = numpy._core._multiarray_umath.__cpu_features__  # X86_V4 is numpy's AVX-512 group; off once disabled
print("numpy AVX-512:", "on" if simd.get("X86_V4") else "off",
    "| opencv:", cv2.getCPUFeaturesLine().split()[-1],
    "| torch:", torch.backends.cpu.get_cpu_capability(), "threads", torch.get_num_threads(),
    "| numba:", numba.config.CPU_NAME or "host",
    "| cores:", len(os.sched_getaffinity(0)))
"""


def _verdicts(junit: Path) -> dict[str, str]:
    verdicts = {}
    for case in ET.parse(junit).getroot().iter("testcase"):
        name = f"{case.get('classname')}::{case.get('name')}"
        kinds = {child.tag for child in case}
        verdicts[name] = "failed" if kinds & {"failure", "error"} else "skipped" if "skipped" in kinds else "passed"
    return verdicts


def run_config(name: str, tests: list[str], workdir: Path) -> tuple[dict[str, str], float]:
    extra_env, prefix = CONFIGS[name]
    env = {**os.environ, "MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa", **extra_env}
    probe = subprocess.run([*prefix, sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, cwd=REPO)
    print(f"[{name}] {(probe.stdout or probe.stderr).strip().splitlines()[-1]}", flush=True)
    junit = workdir / f"{name}.xml"
    cmd = [*prefix, sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "0", f"--junitxml={junit}"]
    tick = time.perf_counter()
    proc = subprocess.run([*cmd, *tests], env=env, capture_output=True, text=True, cwd=REPO)
    seconds = time.perf_counter() - tick
    if not junit.exists():
        print(proc.stdout[-3000:], proc.stderr[-3000:])
        raise SystemExit(f"[{name}] pytest wrote no report (exit {proc.returncode})")
    return _verdicts(junit), seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tests", nargs="+", default=list(DEFAULT_TESTS))
    parser.add_argument("--configs", default=",".join(CONFIGS), help="comma-separated: " + ", ".join(CONFIGS))
    args = parser.parse_args()
    names = [c for c in args.configs.split(",") if c]
    unknown = [c for c in names if c not in CONFIGS]
    if unknown or not names:
        parser.error(f"unknown configuration(s) {unknown}; choose from {', '.join(CONFIGS)}")
    if any(CONFIGS[n][1] for n in names) and shutil.which("taskset") is None:
        parser.error("taskset (util-linux) is needed for one-core")
    workdir = Path(tempfile.mkdtemp(prefix="cpu-switches-"))
    results = {}
    try:
        for name in names:
            results[name], seconds = run_config(name, args.tests, workdir)
            counts = {v: sum(1 for x in results[name].values() if x == v) for v in ("passed", "failed", "skipped")}
            print(
                f"[{name}] {counts['passed']} passed, {counts['failed']} failed, {counts['skipped']} skipped "
                f"in {seconds / 60:.1f} min",
                flush=True,
            )
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    tests = sorted(set().union(*(r.keys() for r in results.values())))
    differing = [t for t in tests if len({results[n].get(t, "missing") for n in names}) > 1]
    failing = [t for t in tests if any(results[n].get(t) == "failed" for n in names)]
    for test in sorted(set(differing) | set(failing)):
        print(f"  {test}: " + ", ".join(f"{n} {results[n].get(test, 'missing')}" for n in names))
    print(f"{len(tests)} tests x {len(names)} configurations: {len(differing)} differ, {len(failing)} fail somewhere")
    sys.exit(1 if differing or failing else 0)


if __name__ == "__main__":
    main()
