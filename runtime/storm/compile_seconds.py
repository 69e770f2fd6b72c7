"""Measured CPU seconds of each storm warm-up task's cold compile in one process (generated: do not
edit; ``NUMBA_CACHE_DIR=$(mktemp -d) HAILSTORM_COMPILE_WORKERS=1 python tests/benchmarks/compile_time.py
--write [--integrator NAME]``).

The fallback of :func:`hailstorm.runtime.storm.warmup.measured_seconds` before a machine has
measured its own.
"""

CPU_S: dict[str, float] = {
}
