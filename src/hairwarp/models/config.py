"""Architecture settings of the HairFormer networks (Sections 3.2, 3.3, 4.3.1, 4.5.2).

Every size lives in one dataclass per network, so a checkpoint can store the settings as a plain
dict (`to_dict`) and rebuild the very same network from it (`from_dict`). The defaults are the
paper's where it states them (d_m = d_z = 512, an 8x8 deformation grid, N = 100 vertices per
strand, T_w = 10, LoRA rank and alpha 4); where it does not (layer counts, heads, FFN and head
widths), the defaults are ordinary Transformer choices, documented field by field.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

# Feature-fusion strategies of the dynamic network (Section 4.5.2).
FUSION_CROSS_ATTENTION = "cross_attention"  # the paper's method: I_sd blocks + functional regularization
FUSION_LAYERNORM_CONCAT = "layernorm_concat"  # ablation (1): LayerNorm both, concatenate, MLP head
FUSION_LORA = "lora"  # ablation (2): I_sd blocks, frozen static head + LoRA instead of Eq. 4
FUSIONS = (FUSION_CROSS_ATTENTION, FUSION_LAYERNORM_CONCAT, FUSION_LORA)

# What follows the tapered deformation of Eq. 2 (`hairwarp.models.deformation.apply_deformation`):
# nothing (the paper), or the follow-the-leader projection onto the rest segment lengths
# (`hairwarp.ops.follow_the_leader`), which makes the drape inextensible by construction.
LENGTH_PROJECTION_NONE = "none"
LENGTH_PROJECTION_FOLLOW_THE_LEADER = "follow_the_leader"
LENGTH_PROJECTIONS = (LENGTH_PROJECTION_NONE, LENGTH_PROJECTION_FOLLOW_THE_LEADER)


def _check_positive_int(owner: str, name: str, value) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
        raise ValueError(f"{owner}.{name}: expected a positive int, got {value!r}")


def _check_length_projection(owner: str, value) -> None:
    if value not in LENGTH_PROJECTIONS:
        raise ValueError(f"{owner}.length_projection: expected one of {list(LENGTH_PROJECTIONS)}, got {value!r}")


def _check_non_negative(owner: str, name: str, value, *, upper: float | None = None) -> None:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and value == value and value >= 0
    if ok and upper is not None:
        ok = value < upper
    if not ok:
        bound = f" below {upper}" if upper is not None else ""
        raise ValueError(f"{owner}.{name}: expected a non-negative number{bound}, got {value!r}")


class _DictConfig:
    """Round trip through plain dicts (what a checkpoint stores)."""

    def to_dict(self) -> dict:
        """The settings as a plain (nested) dict of Python numbers and strings."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict):
        """Rebuild the config from `to_dict`'s output.

        Raises:
            ValueError: on a key that is not a field of the config.
        """
        if not isinstance(data, dict):
            raise ValueError(f"data: expected a dict, got {type(data).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"data: unknown {cls.__name__} fields {unknown}")
        kwargs = dict(data)
        for f in dataclasses.fields(cls):
            sub = _NESTED.get((cls.__name__, f.name))
            if sub is not None and isinstance(kwargs.get(f.name), dict):
                kwargs[f.name] = sub.from_dict(kwargs[f.name])
        return cls(**kwargs)


@dataclass
class StaticConfig(_DictConfig):
    """Static Hair Transformer (Section 3.2, Eq. 3).

    Attributes:
        latent_dim: d_z, size of the hair latent z (512 in the paper).
        model_dim: d_m, width of every Transformer module (512 = d_z in the paper).
        grid_height: M_H0, rows of the deformation map (8 in the paper; rows follow root v).
        grid_width: M_W0, columns of the deformation map (8 in the paper; columns follow root u).
        num_vertices: N, vertices per strand (100 in the paper).
        shape_dim: size of the body shape beta (16).
        pose_dim: size of the body pose Theta (66: 22 joints, axis-angle).
        num_heads: attention heads; the paper does not state it: 8 (64 channels per head).
        num_encoder_layers: N_enc self-attention layers of the hair encoder; not stated: 4.
        num_hair_body_layers: N_hb hair-body cross-attention blocks; not stated: 4.
        ffn_dim: hidden width of every position-wise FFN; not stated: 4 d_m (Transformer habit).
        body_hidden_dim: hidden width of the body MLP encoder E_body.
        head_hidden_dim: hidden width of the prediction head F_pred.
        head_layers: linear layers in the prediction head (>= 1).
        dropout: dropout in attention and FFNs; 0 (a deterministic physics regressor).
        head_init_gain: scale of the head's last layer at initialisation: its weights are
            uniform in +-gain/sqrt(fan_in) and its bias zero, so the initial deformations are
            about a millimetre (the paper: "randomly initialized and clipped at 0.01").
        deformation_clip: the clip the paper applies to the deformations early in static
            training [m]; the networks' `forward(..., clip=...)` applies it when asked.
        length_projection: "none" (the paper: positions = rigid + tapered map) or
            "follow_the_leader" (those positions projected onto the rest segment lengths, so a
            drape never stretches a strand; beyond the paper).
        contact_samples: K > 0 gives the network, per map cell, K sampled vertices of the rigid
            placement against the body (signed distance, push-out vector, offset from the root;
            `hairwarp.models.contact_features`) as an extra token input; 0 is the paper's
            network, which sees the body only through (beta, Theta).
        held_joints: SMPL joint names (`hairwarp.scene.skeleton.JOINT`) whose angles the body
            encoder does not read: it sees the standing pose's (`hairwarp.scene.motion.
            standing_pose`) in their place. () is the paper's network, which reads all 22.
            Beyond the paper: a limb moves the hair only where it touches it, which a network
            with contact features reads from the body; read from Theta, a raised arm lifted
            long hair it never touched (docs/network_diagnosis.md, T21).
    """

    latent_dim: int = 512
    model_dim: int = 512
    grid_height: int = 8
    grid_width: int = 8
    num_vertices: int = 100
    shape_dim: int = 16
    pose_dim: int = 66
    num_heads: int = 8
    num_encoder_layers: int = 4
    num_hair_body_layers: int = 4
    ffn_dim: int = 2048
    body_hidden_dim: int = 512
    head_hidden_dim: int = 512
    head_layers: int = 3
    dropout: float = 0.0
    head_init_gain: float = 1e-3
    deformation_clip: float = 0.01
    length_projection: str = LENGTH_PROJECTION_NONE
    contact_samples: int = 0
    held_joints: tuple = ()

    def __post_init__(self):
        owner = type(self).__name__
        _check_length_projection(owner, self.length_projection)
        from hairwarp.scene.skeleton import JOINT

        if isinstance(self.held_joints, str) or not isinstance(self.held_joints, (tuple, list)):
            raise ValueError(f"{owner}.held_joints: expected a sequence of joint names, got {self.held_joints!r}")
        self.held_joints = tuple(self.held_joints)
        unknown = [j for j in self.held_joints if j not in JOINT]
        if unknown or len(set(self.held_joints)) != len(self.held_joints):
            raise ValueError(f"{owner}.held_joints: expected distinct names of {sorted(JOINT, key=JOINT.get)}, "
                             f"got {list(self.held_joints)}")
        if not isinstance(self.contact_samples, int) or isinstance(self.contact_samples, bool) or self.contact_samples < 0:
            raise ValueError(f"{owner}.contact_samples: expected a non-negative int, got {self.contact_samples!r}")
        for name in (
            "latent_dim", "model_dim", "grid_height", "grid_width", "shape_dim", "pose_dim",
            "num_heads", "num_encoder_layers", "num_hair_body_layers", "ffn_dim",
            "body_hidden_dim", "head_hidden_dim", "head_layers",
        ):
            _check_positive_int(owner, name, getattr(self, name))
        _check_positive_int(owner, "num_vertices", self.num_vertices)
        if self.num_vertices < 3:
            # Vertices 0 and 1 are fixed: a strand needs a third vertex to move at all.
            raise ValueError(f"{owner}.num_vertices: expected at least 3, got {self.num_vertices}")
        if self.model_dim % self.num_heads:
            raise ValueError(
                f"{owner}.model_dim: expected a multiple of num_heads={self.num_heads}, got {self.model_dim}"
            )
        if self.model_dim % 4:
            # The 2D sinusoidal encoding splits d_m into sin/cos halves for rows and columns.
            raise ValueError(f"{owner}.model_dim: expected a multiple of 4, got {self.model_dim}")
        _check_non_negative(owner, "dropout", self.dropout, upper=1.0)
        _check_non_negative(owner, "head_init_gain", self.head_init_gain)
        _check_non_negative(owner, "deformation_clip", self.deformation_clip)

    @property
    def num_cells(self) -> int:
        """L = M_H0 * M_W0, the number of hair tokens and deformation-map cells."""
        return self.grid_height * self.grid_width

    @classmethod
    def tiny(cls) -> StaticConfig:
        """A few-thousand-parameter network for CPU tests (same structure, small sizes)."""
        return cls(
            latent_dim=24, model_dim=32, grid_height=8, grid_width=8, num_vertices=12,
            num_heads=2, num_encoder_layers=1, num_hair_body_layers=1, ffn_dim=64,
            body_hidden_dim=32, head_hidden_dim=32, head_layers=2,
        )

    @classmethod
    def shipped(cls) -> StaticConfig:
        """The size proposed for a shipped checkpoint: d_m = 256, 3 + 3 layers, FFN 3 d_m.

        About 4.4 M parameters (8.4 MiB in half precision); with `DynamicConfig.shipped()` the
        dynamic checkpoint (static network inside) holds about 7.1 M: 13.5 MiB in half
        precision, under a 16 MiB budget. The hair latent stays 512-d. Its drapes are
        projected onto the rest lengths (`length_projection="follow_the_leader"`): trained
        without it, the networks kept the rigid placement (docs/training_diagnosis.md).
        """
        return cls(
            model_dim=256, num_heads=8, num_encoder_layers=3, num_hair_body_layers=3,
            ffn_dim=768, body_hidden_dim=256, head_hidden_dim=256,
            length_projection=LENGTH_PROJECTION_FOLLOW_THE_LEADER,
        )


@dataclass
class DynamicConfig(_DictConfig):
    """Dynamic hair network (Section 3.3) and its ablation variants (Section 4.5.2).

    Attributes:
        static: settings of the static network inside (frozen); `from_static` fills it in.
        motion_dim: D, size of one frame's motion descriptor m^(t); must match what
            `hairwarp.scene.motion.motion_descriptors` produces. The default counts 22 joint
            angular velocities (66), the unposed-gravity rate (3) and 22 joint accelerations
            (66).
        window: T_w, frames of motion descriptors per time step (10 in the paper).
        num_static_dynamic_layers: N_sd static-dynamic cross-attention blocks; not stated: 4.
        motion_hidden_dim: hidden width of the FC layers before the GRU.
        fusion: one of FUSIONS: "cross_attention" (the paper's method), "layernorm_concat" or
            "lora" (the ablations of Section 4.5.2).
        lora_rank: rank of the LoRA adapters of the "lora" variant (4 in the paper).
        lora_alpha: LoRA alpha (4 in the paper); the adapter output is scaled by alpha / rank.
        func_reg_weight: lambda_fr of Eq. 4; the paper does not state it: 1.
    """

    static: StaticConfig = field(default_factory=StaticConfig)
    motion_dim: int = 135
    window: int = 10
    num_static_dynamic_layers: int = 4
    motion_hidden_dim: int = 512
    fusion: str = FUSION_CROSS_ATTENTION
    lora_rank: int = 4
    lora_alpha: float = 4.0
    func_reg_weight: float = 1.0

    def __post_init__(self):
        owner = type(self).__name__
        if isinstance(self.static, dict):
            self.static = StaticConfig.from_dict(self.static)
        if not isinstance(self.static, StaticConfig):
            raise ValueError(f"{owner}.static: expected a StaticConfig, got {type(self.static).__name__}")
        for name in ("motion_dim", "window", "num_static_dynamic_layers", "motion_hidden_dim", "lora_rank"):
            _check_positive_int(owner, name, getattr(self, name))
        if self.fusion not in FUSIONS:
            raise ValueError(f"{owner}.fusion: expected one of {list(FUSIONS)}, got {self.fusion!r}")
        _check_non_negative(owner, "lora_alpha", self.lora_alpha)
        _check_non_negative(owner, "func_reg_weight", self.func_reg_weight)

    @classmethod
    def tiny(cls, motion_dim: int = 9, fusion: str = FUSION_CROSS_ATTENTION) -> DynamicConfig:
        """Small sizes for CPU tests, around `StaticConfig.tiny()`."""
        return cls(
            static=StaticConfig.tiny(), motion_dim=motion_dim, window=3,
            num_static_dynamic_layers=1, motion_hidden_dim=32, fusion=fusion,
        )

    @classmethod
    def shipped(cls, motion_dim: int = 135) -> DynamicConfig:
        """The proposed shipped size, around `StaticConfig.shipped()` (3 I_sd blocks)."""
        return cls(
            static=StaticConfig.shipped(), motion_dim=motion_dim,
            num_static_dynamic_layers=3, motion_hidden_dim=256,
        )


@dataclass
class QuaffureConfig(_DictConfig):
    """Quaffure (adapted) baseline: a convolutional groom-deformation decoder (Section 4.3.1).

    Attributes:
        latent_dim: d_z of the hair latent (512).
        shape_dim: size of beta (16).
        pose_dim: size of Theta (66).
        num_vertices: N, vertices per strand (100).
        channels: feature channels from the first map (512 x 4 x 4) through the three
            transposed convolutions (to 64 x 32 x 32): four entries, the paper's 512 and 64 at
            the ends, halving in between.
        base_size: side of the first feature map (4); each transposed convolution doubles it,
            so the deformation map is base_size * 8 per side (32, the scalp grid).
        head_init_gain: as in StaticConfig: small last layer, millimetre initial deformations.
        deformation_clip: as in StaticConfig [m].
        length_projection: as in StaticConfig.
    """

    latent_dim: int = 512
    shape_dim: int = 16
    pose_dim: int = 66
    num_vertices: int = 100
    channels: tuple = (512, 256, 128, 64)
    base_size: int = 4
    head_init_gain: float = 1e-3
    deformation_clip: float = 0.01
    length_projection: str = LENGTH_PROJECTION_NONE

    def __post_init__(self):
        owner = type(self).__name__
        _check_length_projection(owner, self.length_projection)
        for name in ("latent_dim", "shape_dim", "pose_dim", "num_vertices", "base_size"):
            _check_positive_int(owner, name, getattr(self, name))
        self.channels = tuple(self.channels)
        if len(self.channels) != 4:
            raise ValueError(f"{owner}.channels: expected 4 entries, got {len(self.channels)}")
        for c in self.channels:
            _check_positive_int(owner, "channels", c)
        _check_non_negative(owner, "head_init_gain", self.head_init_gain)
        _check_non_negative(owner, "deformation_clip", self.deformation_clip)

    @property
    def grid_size(self) -> int:
        """Side of the output deformation map (32 for the defaults)."""
        return self.base_size * 8

    @classmethod
    def tiny(cls) -> QuaffureConfig:
        """Small sizes for CPU tests (still a 32x32 output map)."""
        return cls(latent_dim=24, num_vertices=12, channels=(32, 16, 16, 8))


_NESTED = {("DynamicConfig", "static"): StaticConfig}
