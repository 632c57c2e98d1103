"""The dataset on disk: its format, the PyTorch dataset over it, and its checks.

``python -m neuralbokeh.data check ROOT`` validates datasets (``check.py``).
"""
