"""Torch-free foundations every other part may use: checks, optics, apertures, the colour
normalisation, image I/O, CLI helpers. numpy (and OpenImageIO for I/O) only; nothing here
imports another folder of the package."""
