"""Measured CPU seconds of each storm warm-up task's cold compile in one process (generated: do not
edit; ``NUMBA_CACHE_DIR=$(mktemp -d) HAILSTORM_COMPILE_WORKERS=1 python tests/benchmarks/compile_time.py
--write [--integrator NAME]``; last written 2026-12-06 at load 0.9 on 2 CPUs).

The fallback of :func:`hailstorm.runtime.storm.warmup.measured_seconds` before a machine has
measured its own.
"""

CPU_S: dict[str, float] = {
    'the contact-set kernels': 4.82,
    'the contact-step kernels': 1.28,
    "the exact integrator's kernels": 26.06,
    'the free-flight and broad-phase kernels': 1.78,
    'the free-steps kernel': 5.62,
    "the implicit integrator's kernels": 6.77,
    'the narrow-phase kernels': 6.37,
    'the patch kernels': 6.01,
}
