"""Measured CPU seconds of each storm warm-up task's cold compile in one process (generated: do not
edit; ``NUMBA_CACHE_DIR=$(mktemp -d) HAILSTORM_COMPILE_WORKERS=1 python tests/benchmarks/compile_time.py
--write [--integrator NAME]``; last written 2026-12-02 at load 1.2 on 2 CPUs).

The fallback of :func:`hailstorm.runtime.storm.warmup.measured_seconds` before a machine has
measured its own.
"""

CPU_S: dict[str, float] = {
    'the contact-set kernels': 8.34,
    'the contact-step kernels': 2.82,
    "the exact integrator's kernels": 53.61,
    'the free-flight and broad-phase kernels': 3.88,
    "the implicit integrator's kernels": 7.6,
    'the narrow-phase kernels': 11.15,
    'the patch kernels': 11.08,
}
