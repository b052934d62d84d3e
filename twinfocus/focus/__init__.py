"""Focusing: the phase errors estimated and corrected.

Settings and estimators, template matching and the twin-reference autofocus, the reference-free
baselines, the ladder of correction models, the checks of a result, and the pipeline behind
``twinfocus focus`` and the solver node.
"""
