"""Evaluation: the source paper's experiments in simulation, the speed/accuracy trade and the
limits of the method (``twinfocus bench paper``).

Modules: ``experiments`` (the experiments as data), ``cases`` (one simulated scene, its templates,
the methods on error draws, the first-order phase-transfer terms), ``features`` (HOG similarity,
the weight-free second metric), ``trade`` (speed/accuracy knobs and presets), ``runner`` (runs
experiments, keeps raw JSON), ``aggregate`` (means and spreads over the draws, paired gains, limits
rows, trade means), ``figures`` (the report's PNGs), ``report`` (the markdown report and summary
JSON), ``paper`` (the paper's numbers to set beside ours), ``beyond`` (the improvements beyond the
paper).
"""
