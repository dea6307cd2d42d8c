"""Speed against error of every method of the package and of the baselines, in one report.

``sonar-ring bench [--out DIR] [--quick] [--seed N]`` (or ``make bench``) runs
:func:`sonar_ring.benchmark.report.run`: it simulates the standard scenes, runs
every localisation, classification and azimuth method and the baselines on the
same echoes at sigma_t in {0, 0.3, 1, 2} us, times them, and writes
``DIR/BENCHMARKS.md`` with plots in ``DIR/bench/plots/``.

The modules import numpy (and, through the mapper's SLAM, gtsam) at module
level; scipy for the least-squares baseline and matplotlib for the plots are
imported when used; the graph
benchmark (:mod:`sonar_ring.benchmark.graph`) needs rclpy and the built messages.
"""
