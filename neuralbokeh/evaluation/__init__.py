"""Evaluation: metrics, the error-against-run-time report over every method (``evaluate.py``,
``python -m neuralbokeh.evaluation``) and the ablation runner (``ablations.py``)."""
