"""clsplat's benchmarks and reports (installed as ``clsplat.bench``).

* :mod:`.scenes`     the standard scenes A (100k SH-3 Gaussians, one 640x352 camera) and B
                     (pixel-aligned, 6 cameras at 176x320), plus size sweeps;
* :mod:`.limits`     the machine's memory bandwidth (copy kernel) and peak FLOP/s (FMA kernel);
* :mod:`.stages`     per-stage timing with OpenCL profiling events, sort vs numpy, scaling;
* :mod:`.backward`   backward per-stage timing, backward/forward ratio, training steps/s,
                     gradient-slot memory, specialisation gains (part of the stages report);
* :mod:`.precision`  the work-precision diagram (DESIGN.md §6);
* :mod:`.stability`  the stiff and extreme catalogue (DESIGN.md §5) at increasing severity.

* :mod:`.timing`     event milliseconds and the median/min/max/spread summary;
* :mod:`.cli`        ``clsplat bench {stages,precision,stability,all} --out DIR``.

``bench/RESULTS.md`` holds the latest figures. The model experiments behind its model sections
are scripts in ``bench/experiments/`` (not installed).
"""
