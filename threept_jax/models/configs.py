"""Frozen model configurations and the ViT size table.

Variants are named as in big_vision's ``vit.py``: ``"<size>/<patch>"`` (``"B/16"``, ``"L/14"``),
with the size looked up in :data:`VIT_SIZES`. ``"tiny"`` (width 64, depth 2) exists for tests
and the pipeline check, ``"mini"`` (width 128, depth 4) for what 2 CPU cores train in an hour;
their patch size defaults to 16 and may be given (``"tiny/8"``).

Shapes use the letter legend of docs/design.md section 3: B batch, O objects, P patches,
T templates, D width.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax.numpy as jnp
import numpy as np

#: size name -> (width, depth, num_heads, mlp_dim). Ti/S/M/B/L/H are the standard ViT sizes
#: (Dosovitskiy et al. 2021; Steiner et al. 2021; big_vision ``decode_variant``).
VIT_SIZES: dict[str, tuple[int, int, int, int]] = {
    "tiny": (64, 2, 2, 256),
    "mini": (128, 4, 4, 512),
    "Ti": (192, 12, 3, 768),
    "S": (384, 12, 6, 1536),
    "M": (512, 12, 8, 2048),
    "B": (768, 12, 12, 3072),
    "L": (1024, 24, 16, 4096),
    "H": (1280, 32, 16, 5120),
}

#: Patch size used when a variant names no patch (only sensible for the test model).
_DEFAULT_PATCH = {"tiny": 16, "mini": 16}

#: Patch embeddings of the ViT (``ViTConfig.stem``).
STEMS = ("patch", "conv")

#: Tile side the paper's pan-and-scan uses; image sizes default to the nearest patch multiple.
PAPER_TILE_SIZE = 512


def decode_variant(variant: str) -> dict[str, int]:
    """``"B/16"`` -> ``{"width": 768, "depth": 12, "num_heads": 12, "mlp_dim": 3072,
    "patch_size": 16}``."""
    if not isinstance(variant, str) or not variant:
        raise ValueError(f"ViT variant must be a string such as 'B/16', got {variant!r}")
    size, _, patch = variant.partition("/")
    if size not in VIT_SIZES:
        raise ValueError(
            f"unknown ViT size {size!r} in variant {variant!r}; known sizes: "
            f"{', '.join(VIT_SIZES)} (write e.g. 'B/16' or 'tiny')"
        )
    if patch:
        if not patch.isdigit() or int(patch) < 1:
            raise ValueError(f"patch size in {variant!r} must be a positive integer, e.g. 'B/16'")
        patch_size = int(patch)
    elif size in _DEFAULT_PATCH:
        patch_size = _DEFAULT_PATCH[size]
    else:
        raise ValueError(f"variant {variant!r} needs a patch size, e.g. '{size}/16'")
    width, depth, num_heads, mlp_dim = VIT_SIZES[size]
    return dict(width=width, depth=depth, num_heads=num_heads, mlp_dim=mlp_dim,
                patch_size=patch_size)


def _dtype(x: Any) -> np.dtype:
    try:
        return jnp.dtype(x)
    except TypeError as e:
        raise ValueError(f"not a dtype: {x!r} (use e.g. 'float32' or 'bfloat16')") from e


def nearest_patch_multiple(size: int, patch_size: int) -> int:
    """The multiple of ``patch_size`` nearest to ``size`` (ties go up), at least one patch."""
    return max(patch_size, int(np.floor(size / patch_size + 0.5)) * patch_size)


@dataclasses.dataclass(frozen=True)
class ViTConfig:
    """A plain pre-LayerNorm ViT encoder (no class token).

    ``image_size`` is the *native* input side: the learned position embedding has
    ``(image_size // patch_size)**2`` rows and is bilinearly resized for any other grid.
    ``num_registers`` learned register tokens (Darcet et al., "Vision Transformers Need
    Registers", 2024) join the sequence and are dropped from the patch outputs.
    ``layerscale_init``: LayerScale (Touvron et al., CaiT, 2021; used by DINOv2) multiplies each
    residual branch by a learned per-channel vector initialised to this value; ``None`` (the
    default, and the detector's setting) builds no LayerScale and leaves the numerics unchanged.
    ``dtype`` is the compute dtype, ``param_dtype`` the storage dtype; layer norms, softmax and
    the position-embedding resize always run in float32. ``attention_impl`` goes to
    ``jax.nn.dot_product_attention``: ``None``/``"xla"`` everywhere, ``"cudnn"`` for cuDNN flash
    attention on NVIDIA GPUs (bfloat16/float16 compute only). ``stem``: ``"patch"``, the plain
    ViT's one strided patch convolution, or ``"conv"``, a stack of 3x3 stride-2 convolutions
    ending in a 1x1 projection (Xiao et al., "Early Convolutions Help Transformers See Better",
    NeurIPS 2021; :class:`threept_jax.models.vit.ConvStem`), for patch sizes that are powers of two.
    """

    width: int
    depth: int
    num_heads: int
    mlp_dim: int
    patch_size: int
    image_size: int = 224
    num_registers: int = 0
    layerscale_init: float | None = None
    posemb: str = "learned"
    layernorm_epsilon: float = 1e-6
    attention_impl: str | None = None
    remat: bool = False
    stem: str = "patch"
    dtype: Any = jnp.float32
    param_dtype: Any = jnp.float32

    def __post_init__(self):
        object.__setattr__(self, "dtype", _dtype(self.dtype))
        object.__setattr__(self, "param_dtype", _dtype(self.param_dtype))
        for name in ("width", "depth", "num_heads", "mlp_dim", "patch_size", "image_size"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"ViTConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.num_registers < 0:
            raise ValueError(f"ViTConfig.num_registers must be >= 0, got {self.num_registers}")
        if self.layerscale_init is not None and not self.layerscale_init > 0:
            raise ValueError(
                f"ViTConfig.layerscale_init must be > 0 or None (no LayerScale), got "
                f"{self.layerscale_init} (DINOv2 uses 1e-5)"
            )
        if self.width % self.num_heads:
            raise ValueError(
                f"ViT width {self.width} is not divisible by num_heads {self.num_heads}"
            )
        if self.posemb not in ("learned", "sincos2d"):
            raise ValueError(f"posemb must be 'learned' or 'sincos2d', got {self.posemb!r}")
        if self.stem not in STEMS:
            raise ValueError(f"stem must be one of {STEMS}, got {self.stem!r}")
        if self.stem == "conv" and (self.patch_size < 2 or self.patch_size & (self.patch_size - 1)):
            raise ValueError(
                f"the conv stem halves the image log2(patch) times, so the patch size must be a "
                f"power of two >= 2, got {self.patch_size}; use stem='patch' for /14"
            )
        if self.attention_impl not in (None, "xla", "cudnn"):
            raise ValueError(
                f"attention_impl must be None, 'xla' or 'cudnn', got {self.attention_impl!r}"
            )
        if self.posemb == "sincos2d" and self.width % 4:
            raise ValueError(f"sincos2d position embeddings need width % 4 == 0, got {self.width}")
        if self.image_size % self.patch_size:
            raise ValueError(
                f"image_size {self.image_size} is not a multiple of patch_size {self.patch_size}; "
                f"use {nearest_patch_multiple(self.image_size, self.patch_size)}"
            )

    @classmethod
    def from_variant(cls, variant: str, **overrides: Any) -> ViTConfig:
        """``ViTConfig.from_variant("B/16", image_size=512, dtype="bfloat16")``."""
        return cls(**{**decode_variant(variant), **overrides})

    @property
    def native_grid(self) -> tuple[int, int]:
        g = self.image_size // self.patch_size
        return (g, g)

    @property
    def head_dim(self) -> int:
        return self.width // self.num_heads


class _VariantSizes:
    """``width``, ``depth`` and ``patch_size`` of a config's ``variant`` (:func:`decode_variant`)."""

    variant: str

    @property
    def width(self) -> int:
        return decode_variant(self.variant)["width"]

    @property
    def depth(self) -> int:
        return decode_variant(self.variant)["depth"]

    @property
    def patch_size(self) -> int:
        return decode_variant(self.variant)["patch_size"]


@dataclasses.dataclass(frozen=True)
class DetectorConfig(_VariantSizes):
    """3PT-D, the early-fusion two-tower detector (docs/design.md section 1.1).

    Attributes:
      variant: ViT size and patch, parsed by :func:`decode_variant` (``"tiny"``, ``"S/16"``,
        ``"B/16"``, ``"L/14"``).
      image_size: side of the square image tiles fed to ``detect`` (the pan-and-scan tile).
        ``None`` picks the patch multiple nearest 512 (512 for /16, 518 for /14).
      render_size: side of the prior and template renders fed to the object tower.
      num_prior_views: number of fixed prior renders per object (12, icosahedron viewpoints).
      tokens_per_view: pooled tokens per prior view; each view's patch tokens are reduced by
        multi-head attention pooling with this many learned probes, so the prior has
        ``num_prior_views * tokens_per_view`` tokens (4 -> 48 tokens, under 5% of the 1024 patch
        tokens of a 512 tile at /16).
      embed_dim: dimension of hypothesis and template embeddings; ``None`` = backbone width.
      num_registers: register tokens in both towers.
      posemb: ``"learned"`` (resized bilinearly to any grid) or ``"sincos2d"``.
      share_backbone: one ViT for both towers (default) or two. Sharing halves the backbone
        parameters and, more importantly, puts the prior tokens and the image patch tokens in
        the same feature space before fusion, which suits early fusion and the cosine
        comparison of hypotheses with templates. OWL-ViT keeps separate towers because its
        query tower is a text model; ours sees images in both.
      box_head_layers / presence_head_layers: MLP depths of the heads (OWL-ViT: 3 for boxes).
      class_prior: initial presence probability (0.01, RetinaNet/OWL-ViT focal-loss prior).
      logit_scale_init: initial scale of the cosine similarity in orientation logits.
      attention_impl: ``None``/``"xla"``, or ``"cudnn"`` (flash attention, GPU, bf16/fp16).
      remat: rematerialise each transformer block in the backward pass.
      stem: the backbone's patch embedding, ``"patch"`` (the plain ViT's) or ``"conv"``
        (:class:`ViTConfig`).
      dtype / param_dtype: compute and storage dtypes of every layer.
    """

    variant: str = "B/16"
    image_size: int | None = None
    render_size: int = 224
    num_prior_views: int = 12
    tokens_per_view: int = 4
    embed_dim: int | None = None
    num_registers: int = 0
    posemb: str = "learned"
    share_backbone: bool = True
    attention_impl: str | None = None
    box_head_layers: int = 3
    presence_head_layers: int = 2
    class_prior: float = 0.01
    logit_scale_init: float = 10.0
    remat: bool = False
    stem: str = "patch"
    dtype: Any = jnp.float32
    param_dtype: Any = jnp.float32

    def __post_init__(self):
        arch = decode_variant(self.variant)
        p = arch["patch_size"]
        if self.image_size is None:
            object.__setattr__(self, "image_size", nearest_patch_multiple(PAPER_TILE_SIZE, p))
        if self.embed_dim is None:
            object.__setattr__(self, "embed_dim", arch["width"])
        object.__setattr__(self, "dtype", _dtype(self.dtype))
        object.__setattr__(self, "param_dtype", _dtype(self.param_dtype))
        for name, size in (("image_size", self.image_size), ("render_size", self.render_size)):
            if size % p:
                raise ValueError(
                    f"DetectorConfig.{name}={size} is not a multiple of the patch size {p} of "
                    f"{self.variant!r}; use {nearest_patch_multiple(size, p)} (the pan-and-scan "
                    "tile size must match image_size)"
                )
        for name in ("num_prior_views", "tokens_per_view", "embed_dim", "box_head_layers",
                     "presence_head_layers"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"DetectorConfig.{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 < self.class_prior < 1.0:
            raise ValueError(f"class_prior must be in (0, 1), got {self.class_prior}")
        if self.logit_scale_init <= 0:
            raise ValueError(f"logit_scale_init must be > 0, got {self.logit_scale_init}")
        _ = self.vit  # builds (and so validates) the backbone config

    @property
    def vit(self) -> ViTConfig:
        """Backbone config; its native size is the tile size (the renders use a resized grid)."""
        return ViTConfig.from_variant(
            self.variant,
            image_size=self.image_size,
            num_registers=self.num_registers,
            posemb=self.posemb,
            attention_impl=self.attention_impl,
            remat=self.remat,
            stem=self.stem,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
        )

    @property
    def grid_size(self) -> int:
        """Patches per side of an image tile."""
        return self.image_size // self.patch_size

    @property
    def num_patches(self) -> int:
        """P, the number of object hypotheses per tile."""
        return self.grid_size**2

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready fields (dtypes by name); ``DetectorConfig(**d)`` rebuilds the config."""
        d = dataclasses.asdict(self)
        d["dtype"], d["param_dtype"] = np.dtype(self.dtype).name, np.dtype(self.param_dtype).name
        return d

    @property
    def num_prior_tokens(self) -> int:
        """Np = num_prior_views * tokens_per_view."""
        return self.num_prior_views * self.tokens_per_view


#: Each pretrained stem (RefinerConfig.pretrained_stem): the channels of its features.
STEM_CHANNELS = {"xfeat": 64, "aliked": 128}
#: RefinerConfig.pretrained_stem values: none, or one of STEM_CHANNELS.
PRETRAINED_STEMS = ("none", *STEM_CHANNELS)


@dataclasses.dataclass(frozen=True)
class RefinerConfig(_VariantSizes):
    """3PT-R, the render-and-compare refiner network (docs/design.md section 1.3, paper 3.3).

    Attributes:
      variant: ViT size and patch, parsed by :func:`decode_variant` (``"tiny/16"``, ``"S/14"``,
        ``"L/14"``). One encoder embeds the real crops and the renders.
      crop_size: H = W, the side of the square crops fed to the network; a patch multiple.
      num_registers: register tokens of the encoder (DINOv2 with registers: 4). At least one:
        the first register after cross-attention gives the score.
      layerscale_init: initial LayerScale of every residual branch (encoder and cross-attention
        blocks); 1e-5 as DINOv2; ``None`` builds no LayerScale.
      descriptor_dim: C, the dimension of the unit descriptors F and Z.
      cross_attention_layers: CroCo-style blocks in which each real view's tokens attend to
        the render tokens of that view under one hypothesis.
      output_size: h = w, the side of the descriptor and mask maps; ``None`` = 4 * crop_size /
        patch, the resolution of DPT's finest reassembled level (stride patch / 4: 64 for a
        224 crop at /14). Any other size is reached by bilinear (pixel-centre) resizing in the
        last fusion step; the map is the crop resized to h x h, pixel centres aligned.
      dpt_features: width of DPT's fusion path (Ranftl et al. 2021: 256); the reassembled
        levels have widths (D/4, D/2, D, D) (DPT-Large's 256, 512, 1024, 1024 at D = 1024).
      conditioned_levels: how many of DPT's four levels of the real crop (coarsest first) are
        reassembled from the cross-attention output, and so depend on the hypothesis; the
        finer ones come from the encoder alone and are shared by every hypothesis. 1: the
        fourth level only (stride 2 patches: 2 x 2 for 64 px crops at /16).
      pixel_features: width of a convolutional stem on the crop itself (two 3 x 3 convolutions
        at the crop's resolution, resized to the map) whose features join DPT's output before
        the heads: DPT sees the image only through patch tokens, and a small network does not
        learn where inside a patch an edge lies (measured in docs/training.md, "3PT-R:
        matching on unseen parts per CPU minute"). 0: none, the paper's decoder.
      pretrained_stem: ``"none"``, ``"xfeat"`` or ``"aliked"``: a pretrained XFeat
        (:mod:`threept_jax.models.xfeat`, stride-8 64-channel features) or ALIKED
        (:mod:`threept_jax.models.aliked`, ``aliked-n16``, stride-1 128-channel features),
        BatchNorms folded, reads every crop; its features enter twice: resized to the patch
        grid, through a linear layer (zero at initialisation) added to the patch embeddings,
        and resized to the map, joined to DPT's output before the heads (as the pixel stem's).
        Crop sizes in multiples of 32. The trainer loads the pretrained weights into a fresh
        run (``models/<stem>``); ``optim.freeze = "stem"`` holds them fixed.
      stem_descriptors: the descriptor maps start as the pretrained stem's features: F =
        unit(stem features resized to the map + the descriptor head's output), the head zero
        at initialisation, so a fresh network matches as the stem's features matched directly
        (:class:`threept_jax.models.aliked.ALIKEDDescriptors` with ``sddh=False``) and
        training learns a correction. Needs ``descriptor_dim`` equal to the stem's channels
        (:data:`STEM_CHANNELS`).
      attention_impl: ``None``/``"xla"``, or ``"cudnn"`` (flash attention, GPU, bf16/fp16).
      remat: rematerialise each encoder, cross-attention and DPT fusion block (and the DPT
        head) in the backward pass.
      dtype / param_dtype: compute and storage dtypes of every layer.
    """

    variant: str = "S/14"
    crop_size: int = 224
    num_registers: int = 4
    layerscale_init: float | None = 1e-5
    descriptor_dim: int = 128
    cross_attention_layers: int = 4
    output_size: int | None = None
    dpt_features: int = 256
    conditioned_levels: int = 1
    pixel_features: int = 0
    pretrained_stem: str = "none"
    stem_descriptors: bool = False
    attention_impl: str | None = None
    remat: bool = False
    dtype: Any = jnp.float32
    param_dtype: Any = jnp.float32

    def __post_init__(self):
        arch = decode_variant(self.variant)
        p = arch["patch_size"]
        if not 1 <= int(self.conditioned_levels) <= 4:
            raise ValueError(f"RefinerConfig.conditioned_levels must be 1 to 4 (DPT levels of "
                             f"the real crop that read the cross-attention output), got "
                             f"{self.conditioned_levels}")
        if int(self.pixel_features) < 0:
            raise ValueError(f"RefinerConfig.pixel_features must be >= 0 (0: no pixel stem), "
                             f"got {self.pixel_features}")
        if self.pretrained_stem not in PRETRAINED_STEMS:
            raise ValueError(f"RefinerConfig.pretrained_stem must be one of {PRETRAINED_STEMS}, "
                             f"got {self.pretrained_stem!r}")
        if self.pretrained_stem != "none" and self.crop_size % 32:
            m = math.lcm(32, p)  # and of the patch size
            raise ValueError(f"RefinerConfig.pretrained_stem={self.pretrained_stem!r} needs a "
                             f"crop_size in multiples of 32 (the network's coarsest stride), got "
                             f"{self.crop_size}; use {-(-self.crop_size // m) * m}")
        if self.stem_descriptors and STEM_CHANNELS.get(self.pretrained_stem) != self.descriptor_dim:
            raise ValueError(f"RefinerConfig.stem_descriptors needs a pretrained_stem and a "
                             f"descriptor_dim equal to its channels {STEM_CHANNELS}, got "
                             f"{self.pretrained_stem!r} and {self.descriptor_dim}")
        if self.crop_size % p:
            raise ValueError(
                f"RefinerConfig.crop_size={self.crop_size} is not a multiple of the patch size "
                f"{p} of {self.variant!r}; use {nearest_patch_multiple(self.crop_size, p)}"
            )
        if self.output_size is None:
            object.__setattr__(self, "output_size", 4 * (self.crop_size // p))
        object.__setattr__(self, "dtype", _dtype(self.dtype))
        object.__setattr__(self, "param_dtype", _dtype(self.param_dtype))
        for name in ("crop_size", "num_registers", "descriptor_dim", "cross_attention_layers",
                     "output_size", "dpt_features"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"RefinerConfig.{name} must be >= 1, got {getattr(self, name)}")
        if arch["width"] % 4:
            raise ValueError(f"the DPT levels need a ViT width divisible by 4, got {arch['width']}")
        if self.dpt_features % 2:
            raise ValueError(f"RefinerConfig.dpt_features must be even, got {self.dpt_features}")
        _ = self.vit  # builds (and so validates) the encoder config

    @property
    def vit(self) -> ViTConfig:
        """The encoder (and cross-attention block) config: native size = the crop size."""
        return ViTConfig.from_variant(
            self.variant,
            image_size=self.crop_size,
            num_registers=self.num_registers,
            layerscale_init=self.layerscale_init,
            attention_impl=self.attention_impl,
            remat=self.remat,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
        )

    @property
    def grid_size(self) -> int:
        """Patches per side of a crop."""
        return self.crop_size // self.patch_size

    @property
    def dpt_dims(self) -> tuple[int, int, int, int]:
        """Widths of DPT's four reassembled levels (strides patch/4, patch/2, patch, 2 patch)."""
        d = self.width
        return (d // 4, d // 2, d, d)

    @property
    def encoder_hooks(self) -> tuple[int, int, int, int]:
        """0-based encoder blocks feeding DPT: the last of each quarter of the depth (DPT-Large:
        5, 11, 17, 23 of 24; ViT-B: 2, 5, 8, 11). The real crop's fourth level is the
        cross-attention output instead of the last block."""
        depth = self.depth
        return tuple(-(-depth * (i + 1) // 4) - 1 for i in range(4))  # ceil(depth (i+1)/4) - 1

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready fields (dtypes by name); ``RefinerConfig(**d)`` rebuilds the config."""
        d = dataclasses.asdict(self)
        d["dtype"], d["param_dtype"] = np.dtype(self.dtype).name, np.dtype(self.param_dtype).name
        return d


#: Named refiner sizes (overrides of :class:`RefinerConfig`), read by
#: :func:`get_refiner_config`.
#:
#: - ``tiny``: tests and the demo; tiny/16 (width 64, depth 2) at 64 px crops, maps 32 x 32.
#:   LayerScale starts at 0.1, CaiT's value for shallow networks, so that short CPU runs are
#:   not spent growing 1e-5 gammas.
#: - ``cpu``: what 2 CPU cores train in an hour; mini/16 (width 128, depth 4) at 64 px crops,
#:   maps 32 x 32.
#: - ``small``: one GPU; DINOv2-S/14 shape with 4 registers at 224 px, maps 64 x 64, bf16.
#: - ``paper``: DINOv2-L/14 with registers at 224 px, maps 64 x 64, bf16 compute, float32
#:   parameters, rematerialised blocks.
REFINER_SIZES: dict[str, dict[str, Any]] = {
    "tiny": dict(variant="tiny/16", crop_size=64, output_size=32, layerscale_init=0.1,
                 descriptor_dim=32, cross_attention_layers=1, dpt_features=32),
    "cpu": dict(variant="mini/16", crop_size=64, output_size=32, layerscale_init=0.1,
                descriptor_dim=64, cross_attention_layers=2, dpt_features=64),
    "small": dict(variant="S/14", crop_size=224, descriptor_dim=128, cross_attention_layers=4,
                  dpt_features=128, dtype="bfloat16"),
    "paper": dict(variant="L/14", crop_size=224, descriptor_dim=128, cross_attention_layers=8,
                  dpt_features=256, dtype="bfloat16", remat=True),
}


def get_refiner_config(name: str, **overrides: Any) -> RefinerConfig:
    """``get_refiner_config("small", dtype="float32")``: a named size with field overrides."""
    if name not in REFINER_SIZES:
        raise ValueError(f"unknown refiner size {name!r}; known sizes: {', '.join(REFINER_SIZES)}")
    return RefinerConfig(**{**REFINER_SIZES[name], **overrides})
