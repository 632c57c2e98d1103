"""The network's configuration: everything needed to rebuild either architecture (torch-free).

A checkpoint stores ``ModelConfig.to_dict()`` beside its data contract
(:class:`neuralbokeh.core.contract.Contract`: image size, normalisation, CoC scale, lens,
aperture); :func:`neuralbokeh.networks.build_model` rebuilds the network from the two. The
``[model]`` table of a training config *is* this class (``blocks = "auto"`` is resolved from the
data's largest CoC by :meth:`ModelConfig.resolved`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

from ..core.tiling import TileLayout

ARCHITECTURES = ("lens", "paper")
PUPIL_INITS = ("disk", "gaussian", "aperture")
FILLS = ("background", "normalize", "far_light")
BAND_BLENDS = ("hat", "hermite")
# the bound of the pixel blur's variance (px^2 per axis): its 3-tap filter [v/2, 1 - v, v/2] stays
# within a tent (v = 0.5) and a mild sharpening
PIXEL_BLUR_MAX_PX2 = 0.5
# coverage (of 1) below which the surface fill's mean colour gives way to the background estimate
# (``model.surface_fill``; the module and its ONNX graph share it)
SURFACE_FILL_EPS = 1e-3
# px from a pixel that hides something within which the surface fill keeps the sharp estimate: an
# anti-aliased silhouette pixel mixes the occluder's colour with the surface's under the surface's
# depth, and its truth is nearly that sharp mix (docs/network.md, "The surface fill")
SILHOUETTE_PX = 1
# what a checkpoint written before a key existed meant by leaving it out, where the default has
# changed since: its network is rebuilt as it was trained
LEGACY_DEFAULTS = {"near_focus_px": 0.0, "pixel_blur": False, "surface_fill": False, "occlusion_margin_learned": False,
                   "occlusion_margin_step": False, "occlusion_margin_slope": False, "occlusion_source_coc": False, "field_flow": False,
                   "field_gradient": False, "occlusion_source_coc_grid": 1, "highlight_spread": False}
# the switches: each must be true or false
BOOLEAN_FIELDS = ("vignetting", "occlusion_margin_learned", "occlusion_margin_step", "occlusion_margin_slope", "occlusion_source_coc",
                  "surface_fill", "field_flow", "field_gradient", "pixel_blur", "highlight_spread")
KERNEL_SIZES = ("growing", "fixed3")
TILINGS = ("overlap", "none", "no_overlap")
HEADS = ("identity", "paper")
# the identity head scales tanh(d) by this: 1 + rgb * tanh(d) stays > 0 for inputs of exactly +-1
TANH_LIMIT = 1.0 - 1e-6


@dataclass(frozen=True)
class ModelConfig:
    """The network's hyper-parameters (stored in every checkpoint; the image size, normalisation
    and CoC scale come from the data contract).

    Args:
        architecture: ``"lens"`` (default: :class:`neuralbokeh.networks.lens.LensBokeh`, the
            skeleton with a learned lens) or ``"paper"`` (:class:`neuralbokeh.networks.paper.PaperBokeh`,
            the paper as written).
        blocks: number N of residual blocks, >= 0, or ``"auto"``: from the data's largest CoC
            (``optics.blocks_for_coc``), resolved before a network is built.
        features: feature channels per tile, >= 1.
        tile: tile core size t (px), >= 1.
        overlap: extra context t_o on every side of a tile (px), 0 <= 2 t_o <= t.
        tiling: ``"overlap"`` (the paper), ``"no_overlap"`` (t_o forced to 0) or ``"none"``
            (one tile covering the image).
        kernel_sizes: ``"growing"`` (2n+1, the paper) or ``"fixed3"`` (ablation).
        head: ``"identity"`` or ``"paper"`` (see :mod:`neuralbokeh.networks.paper`).
        fft_min_kernel: kernel size from which per-channel convolutions use the FFT (no grad).
        fft_min_kernel_train: the same when gradients are computed.
        pupil_size: samples per side of each learned pupil grid (lens), >= 4.
        field_grid: nodes per side of the grid over the sensor from which each tile's pupil
            correction is interpolated at its position (lens), >= 1 (1: one pupil everywhere).
        pupil_init: the lens architecture's starting pupil: ``"disk"``, ``"gaussian"`` (the
            baseline's profile) or ``"aperture"`` (the data's aperture shape, from the contract).
        vignetting: learn a cat-eye (lens): the pupil clipped by a circle (the barrel's image,
            at the start 3 pupil-grid steps wider than the aperture and centred) that moves
            across the pupil in proportion to the field position; the field grid learns what
            it leaves.
        occlusion_margin_px: CoC difference (px) over which light changes from "same surface"
            to "in front of / behind" the receiving pixel (lens), > 0.
        occlusion_margin_rel: the margin grows with the band's diameter ``d``: ``max(
            occlusion_margin_px, occlusion_margin_rel * d)`` (lens, >= 0; 0: fixed). A sloped
            surface at a large CoC spans several px of CoC across a blur's reach; a fixed 2 px
            margin makes its nearer part occlude its farther part.
        occlusion_margin_step: each band's margin is at least the band lattice's step there
            (lens; :meth:`~neuralbokeh.core.bands.BandPlan.band_step_px`). Without
            ``occlusion_source_coc`` a band's light carries its centre's CoC, up to a step from a
            receiver on the same plane facing the camera, so a narrower margin splits one plane
            into nearer and farther light; with it (the default) the floor is not needed.
        occlusion_margin_slope: each receiving pixel's margin is at least its own surface's CoC
            change across the band's reach, ``|grad c| * d / 2`` (lens;
            :func:`~neuralbokeh.networks.lens.coc_slope`: each axis' one-sided difference of the
            smaller size, 0 where the two differ in sign, so a depth edge is not a slope).
            Planes facing the camera keep the margin above.
        occlusion_source_coc: each source pixel's CoC travels with its light (lens): its offset
            from its band's centre is scattered with the light (by the green channel's kernel), and
            the buckets compare a receiver with the mean CoC of the light's sources, not with the
            band's centre (:func:`~neuralbokeh.networks.lens.mean_source_coc`). A plane facing
            the camera then stays one surface under any margin, so the step floor is not
            needed, and surfaces closer than a step still part.
        occlusion_source_coc_grid: the carried CoC is scattered on a grid this many times
            coarser than its band's light (an integer >= 1; 1: the light's own grid). A mean
            over a kernel's reach is smooth at that reach; on the light's own grid the carry is
            two more channels convolved at full resolution per band.
        occlusion_margin_learned: learn a factor on that margin (lens; 1 at the start, the
            same for every band): how far apart in CoC two pixels may be and still be one
            surface depends on the data (how its depth was made, how its surfaces slope).
        fill: what the lens architecture puts where its coverage falls short (what a blurred
            foreground uncovers): ``"background"`` (the visible background around the occluder,
            as the reference renderer's default), ``"normalize"`` (divide by the coverage) or
            ``"far_light"`` (the mean colour of the light from behind that reaches the pixel, for
            up to a learned gain times that light's own coverage, the rest the background).
        surface_fill: learn what fills the coverage a pixel's own surface leaves short where that
            pixel stands in front of nothing (lens; ``fill = "background"`` or ``"far_light"``;
            ``"normalize"`` fills nothing): a share (learned, 0.95 at the start) of the mean
            colour of the light arriving from its own depth and behind (at most the bound the
            estimate puts on its own colour), the rest its own sharp colour; pixels within
            ``SILHOUETTE_PX`` of an occluder keep the sharp colour. Next to a sharp foreground a
            blurred background's hidden part is that surface blurred, not the sharp pixel the
            ``"background"`` estimate gives (which the reference renderer uses; the share
            learns which the data has).
        band_blend: how a pixel between two band centres gets its kernel (lens): ``"hat"`` (the
            linear blend of the two band kernels) or ``"hermite"`` (the cubic Hermite
            interpolation of the two kernels and their slopes in the CoC: each band scatters a
            second feature by its kernel's derivative in the diameter; about a quarter of the
            hat's kernel error, for twice the convolutions).
        near_focus_px: the band lattice's near-focus term ``a`` (px, >= 0; lens): the bands are
            uniform in ``|c| + a (1 - 1 / |c|)``, so ``1 + a / |c|^2`` times denser near focus,
            where a blend of a point and a 3 px disk is far from a highlight's 1.5 px disk;
            ``blocks = "auto"`` then adds about ``a / 2`` bands. 0: uniform in |c|.
        pixel_blur: learn a blur the frame's pixels add to every defocused kernel beyond the
            pupil rasterised by area (lens): a per-axis variance ``v(d) = v_inf (1 - exp(-d /
            d_v))`` px^2 at CoC ``d``, zero in focus, ``|v_inf| < 0.5`` (negative: sharper than
            the area raster), ``d_v`` learned from 1 px. E.g. a refocused light field splats
            each view bilinearly: a tent where the raster has a box (+1/12 px^2). Off by
            default: where the truth is the area raster or sharper it learned a sharpening
            that cost held-out accuracy (``docs/network.md``).
        pixel_blur_px2: the starting ``v_inf`` (px^2, in (-0.5, 0.5); 0, the default: the area
            raster exactly), with ``pixel_blur`` only.
        field_flow: move each source pixel's light by where its own pupil's centroid lies
            relative to its tile's (lens): a tile's kernels are its pupil's at the tile's
            centre, and across a tile the cat-eye moves a spot by up to a tenth of its radius
            and more on small frames. Band ``n``'s features are sampled at ``p - f(p)``, ``f =
            d_n / 2 x (mu(p) - mu(tile))`` (the channels' mean centroid, in aperture radii) before
            the scatter, which with the drift's colour gain (its Jacobian) moves the light as
            the per-pixel pupil would, to first order. Skipped where the pupils do not vary. Off
            by default (``field_gradient`` replaces it); set ``field_gradient`` false with it.
        field_gradient: give each source pixel the first-order change of its tile's kernels
            across the tile (lens): band ``n`` also scatters (colour x gate, gate) x the pixel's
            offset from the tile's centre (px, x and y) by the kernels' derivative in the sensor
            position. Across a tile the cat-eye's circle moves over the pupil, which changes a
            kernel's shape, not only where it lands; the derivative holds both, so it replaces
            ``field_flow``, whose bilinear warp also smears what it moves. Three scatters per
            band instead of one (one grouped convolution of three feature groups in the
            export); skipped where the pupils do not vary. On by default.
        highlight_spread: an isolated highlight (a pixel brighter than 3 times its 8
            neighbours' mean) is a light smaller than its pixel, at an unknown place in it: it
            gets the disk whose area raster is nearest the raster blurred by one more pixel box
            (``core.bands.highlight_coc``): ``sqrt(c^2 + (4/3)(1 - c^2/4))`` px from 1 to 2 px,
            ``c`` from 2 px on; below 1 px ``c`` times 1.41, so a highlight at 0.71-1 px leaves
            band 0. Parameter-free; on by default (``docs/network.md``).
        (``features``, ``head`` and the FFT thresholds: paper only; ``pupil_*``,
        ``field_grid``, ``vignetting``, ``occlusion_margin*``, ``fill``, ``surface_fill``,
        ``band_blend``, ``near_focus_px``, ``pixel_blur*``, ``field_flow``, ``field_gradient``,
        ``highlight_spread``: lens only; the rest: both.)
    """

    architecture: str = "lens"
    blocks: int | str = "auto"
    features: int = 12
    tile: int = 200
    overlap: int = 60
    tiling: str = "overlap"
    kernel_sizes: str = "growing"
    head: str = "identity"
    fft_min_kernel: int = 15
    fft_min_kernel_train: int = 5
    pupil_size: int = 48
    pupil_init: str = "disk"
    field_grid: int = 5
    vignetting: bool = True
    occlusion_margin_px: float = 2.0
    occlusion_margin_rel: float = 0.0
    occlusion_margin_learned: bool = True
    occlusion_margin_step: bool = False
    occlusion_margin_slope: bool = True
    occlusion_source_coc: bool = True
    occlusion_source_coc_grid: int = 2
    fill: str = "background"
    surface_fill: bool = True
    band_blend: str = "hat"
    near_focus_px: float = 4.0
    pixel_blur: bool = False
    pixel_blur_px2: float = 0.0
    field_flow: bool = False
    field_gradient: bool = True
    highlight_spread: bool = True

    def __post_init__(self) -> None:
        for name in ("features", "tile", "fft_min_kernel", "fft_min_kernel_train", "occlusion_source_coc_grid"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"model.{name} must be an integer >= 1, got {v!r}")
        for name in BOOLEAN_FIELDS:
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"model.{name} must be true or false, got {getattr(self, name)!r}")
        if self.blocks != "auto" and (isinstance(self.blocks, bool) or not isinstance(self.blocks, int) or self.blocks < 0):
            raise ValueError(f"model.blocks must be an integer >= 0 or 'auto', got {self.blocks!r}")
        if not isinstance(self.overlap, int) or self.overlap < 0 or 2 * self.overlap > self.tile:
            raise ValueError(f"model.overlap must be an integer with 0 <= 2 * overlap <= tile ({self.tile}), got {self.overlap!r}")
        if isinstance(self.field_grid, bool) or not isinstance(self.field_grid, int) or self.field_grid < 1:
            raise ValueError(f"model.field_grid must be an integer >= 1, got {self.field_grid!r}")
        if not isinstance(self.pupil_size, int) or self.pupil_size < 4:
            raise ValueError(f"model.pupil_size must be an integer >= 4, got {self.pupil_size!r}")
        a = self.near_focus_px
        if isinstance(a, bool) or not (isinstance(a, (int, float)) and math.isfinite(a) and a >= 0):
            raise ValueError(f"model.near_focus_px must be a finite number >= 0 px, got {a!r}")
        if self.field_gradient and self.field_flow:
            raise ValueError("model.field_flow and model.field_gradient are both true: the gradient (the default) already gives "
                             "each pixel its own pupil's blur, which the flow would move again; set model.field_gradient = false "
                             "to use the flow, or model.field_flow = false")
        v = self.pixel_blur_px2
        if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and abs(v) < PIXEL_BLUR_MAX_PX2):
            raise ValueError(f"model.pixel_blur_px2 must be a number in (-{PIXEL_BLUR_MAX_PX2}, {PIXEL_BLUR_MAX_PX2}) px^2, got {v!r}")
        if v and not self.pixel_blur:
            raise ValueError(f"model.pixel_blur_px2 = {v!r} starts a learned pixel blur: set model.pixel_blur = true, or leave it 0")
        r = self.occlusion_margin_rel
        if isinstance(r, bool) or not (isinstance(r, (int, float)) and math.isfinite(r) and r >= 0):
            raise ValueError(f"model.occlusion_margin_rel must be a finite number >= 0, got {r!r}")
        m = self.occlusion_margin_px
        if not (isinstance(m, (int, float)) and math.isfinite(m) and m > 0):
            raise ValueError(f"model.occlusion_margin_px must be a finite number > 0 px, got {m!r}")
        for name, allowed in (("tiling", TILINGS), ("kernel_sizes", KERNEL_SIZES), ("head", HEADS),
                              ("architecture", ARCHITECTURES), ("pupil_init", PUPIL_INITS), ("fill", FILLS),
                              ("band_blend", BAND_BLENDS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"model.{name} must be one of {allowed}, got {getattr(self, name)!r}")

    def resolved(self, max_coc_px: float) -> ModelConfig:
        """This config with ``blocks = "auto"`` replaced by N for the data's largest |CoC| (px):
        the fewest bands at most 2 px of lattice coordinate apart (``2N + 1 >= max CoC`` on a
        lattice uniform in |c|, ``optics.blocks_for_coc``)."""
        from ..core.bands import lattice_blocks
        from ..core.optics import blocks_for_coc

        if self.blocks != "auto":
            return self
        n = blocks_for_coc(max_coc_px)  # (which also refuses a negative or non-finite CoC)
        if self.architecture == "lens":
            n = lattice_blocks(max_coc_px, float(self.near_focus_px))
        return replace(self, blocks=n)

    def check_resolved(self) -> None:
        """Raise ``ValueError`` while ``blocks`` is still ``"auto"`` (a network needs N)."""
        if not isinstance(self.blocks, int):
            raise ValueError(f"model.blocks must be resolved to an integer before building a network "
                             f"(ModelConfig.resolved), got {self.blocks!r}")

    def layout(self, height: int, width: int) -> TileLayout:
        """The tile grid over an ``height x width`` image."""
        return TileLayout.for_image(height, width, self.tile, self.overlap, self.tiling)

    def occlusion_margin(self, diameter_px: float) -> float:
        """The buckets' margin (px of CoC) for light of a band of diameter ``diameter_px``, before
        the learned factor (``occlusion_margin_learned``, ``LensBokeh.occlusion_margin``)."""
        return max(float(self.occlusion_margin_px), float(self.occlusion_margin_rel) * float(diameter_px))

    def kernel_size(self, n: int) -> int:
        """Kernel size of residual block n (1-based)."""
        return 3 if self.kernel_sizes == "fixed3" else 2 * n + 1

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> ModelConfig:
        """Read :meth:`to_dict`'s output (a checkpoint's); a key left out takes the value it had
        before the key existed (:data:`LEGACY_DEFAULTS`), else the dataclass's default."""
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown model config keys {sorted(unknown)}; expected {sorted(known)}")
        return cls(**(LEGACY_DEFAULTS | d))
