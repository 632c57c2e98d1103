"""neuralbokeh: learn a real lens's out-of-focus blur and apply it to all-in-focus images.

Units throughout: linear scene-referred RGB (HDR), depth and focus distances in metres, lens
figures in millimetres, circles of confusion as diameters in pixels.

Importing the package has no side effects and does not import torch; import the submodules
you need (``neuralbokeh.core.optics``, ``neuralbokeh.core.apertures``, ``neuralbokeh.render``, ...).
"""

__version__ = "0.1.0"
