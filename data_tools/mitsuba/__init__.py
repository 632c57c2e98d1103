"""Physically rendered focal stacks with Mitsuba 3: ``python -m data_tools.mitsuba``.

``variant`` picks the Mitsuba variant (probed in a subprocess, so a broken LLVM cannot crash
the tool) and imports mitsuba; ``scenes`` builds procedural scenes or loads a user's XML;
``render`` renders the all-in-focus image, planar depth and defocused slices with any
aperture shape and cat-eye vignetting. Nothing here imports mitsuba at import time.
"""
