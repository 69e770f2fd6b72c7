"""Measured CPU seconds of each storm warm-up task's cold compile in one process (generated: do not
edit; ``NUMBA_CACHE_DIR=$(mktemp -d) HAILSTORM_COMPILE_WORKERS=1 python tests/benchmarks/compile_time.py
--write [--integrator NAME]``; last written 2026-12-01 at load 7.4 on 2 CPUs).

The fallback of :func:`hailstorm.runtime.storm.warmup.measured_seconds` before a machine has
measured its own.
"""

CPU_S: dict[str, float] = {
    'the contact-set kernels': 3.89,
    'the contact-step kernels': 3.39,
    'the free-flight and broad-phase kernels': 5.38,
    "the implicit integrator's kernels": 19.56,
    'the narrow-phase kernels': 14.09,
    'the patch kernels': 14.12,
}
