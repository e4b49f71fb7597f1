"""The dynamic hair network (HairFormer Section 3.3) and its fusion ablations (Section 4.5.2).

Per time step t: C_dyn(t) = GRU(FC([m, beta]) over the T_w-frame window, from C_dyn(t-1))
(Section 3.3.1); H_dyn(t) = I_sd*(H_static(t), C_dyn(t)) (Section 3.3.2); D_dyn(t) =
Reshape(F_pred_dyn(H_dyn(t))) (Section 3.3.3). H_static(t) comes from the pre-trained static
network, frozen inside this one (Section 4.2.2). F_pred_dyn starts as a copy of F_pred_static and
the functional regularization of Eq. 4 keeps it close on static features.

Fusion variants (`DynamicConfig.fusion`):
    "cross_attention": the paper's method, above.
    "layernorm_concat": no I_sd; [LayerNorm(H_static), LayerNorm(C_dyn)] concatenated per token
        into an MLP head of input 2 d_m (its H half starts as the static head's first layer,
        its C half at zero), with Eq. 4 evaluated on [LayerNorm(H_static), 0] (no dynamic
        context). The LayerNorm makes Eq. 4 small but not zero at initialisation.
    "lora": I_sd as in the paper; the head is the frozen static head plus rank-r LoRA adapters
        (rank 4, alpha 4) and Eq. 4 is not used (`functional_regularization` returns 0).
"""

from __future__ import annotations

import copy
import dataclasses
from typing import NamedTuple

import torch
from torch import nn

from hairwarp._validate import check_tensor
from hairwarp.models.config import (
    FUSION_LAYERNORM_CONCAT,
    FUSION_LORA,
    DynamicConfig,
)
from hairwarp.models.deformation import apply_deformation
from hairwarp.models.layers import (
    CrossAttentionBlock,
    PredictionHead,
    check_batch,
    clip_deformation,
    mlp,
    reshape_map,
    with_lora,
)
from hairwarp.models.static import StaticNetwork


class DynamicOutput(NamedTuple):
    """What the dynamic network returns.

    Attributes:
        deformation_map: D_dyn [m], (B, M_H0, M_W0, N, 3) from `forward`,
            (B, T, M_H0, M_W0, N, 3) from `simulate`.
        hidden: C_dyn after the last step, (B, d_m): pass it to the next call.
        static_features: H_static of the frozen static network (no gradient), (B, L, d_m) or
            (B, T, L, d_m): the input of `functional_regularization`.
    """

    deformation_map: torch.Tensor
    hidden: torch.Tensor
    static_features: torch.Tensor


def _concat_head_from(static_head: PredictionHead, model_dim: int) -> PredictionHead:
    """A head of input 2 d_m whose H half is the static head and whose C half starts at zero."""
    first = static_head.net[0]
    head = PredictionHead(
        2 * model_dim,
        first.out_features,
        sum(isinstance(m, nn.Linear) for m in static_head.net),
        static_head.net[-1].out_features // 3,
        0.0,
    ).to(dtype=first.weight.dtype, device=first.weight.device)
    with torch.no_grad():
        state = {k: v.clone() for k, v in static_head.state_dict().items()}
        w = state["net.0.weight"]
        state["net.0.weight"] = torch.cat([w, torch.zeros_like(w)], dim=1)
        head.load_state_dict(state)
    return head


class DynamicNetwork(nn.Module):
    """Dynamic hair network: (z, beta, Theta, motion window, C_dyn) -> (D_dyn, next C_dyn).

    The static network is a frozen submodule (`requires_grad` False, kept in eval mode):
    `trainable_parameters()` is what an optimizer should take. Its checkpoint therefore holds
    the static weights as well and is self-contained.

    Args:
        config: sizes and fusion variant; `config.static` must match `static`'s config.
        static: the pre-trained static network. It is frozen in place (its parameters'
            `requires_grad` set to False). None builds a fresh one from `config.static`
            (used when loading a checkpoint, whose weights then replace it).
    """

    kind = "dynamic"

    def __init__(self, config: DynamicConfig, static: StaticNetwork | None = None):
        super().__init__()
        if not isinstance(config, DynamicConfig):
            raise ValueError(f"config: expected a DynamicConfig, got {type(config).__name__}")
        if static is None:
            static = StaticNetwork(config.static)
        if not isinstance(static, StaticNetwork):
            raise ValueError(f"static: expected a StaticNetwork, got {type(static).__name__}")
        if static.config != config.static:
            raise ValueError("config: config.static differs from the static network's config")
        self.config = config
        scfg = config.static
        d = scfg.model_dim
        dtype = next(static.parameters()).dtype
        device = next(static.parameters()).device

        # Section 3.3.1: FC layers on [m, beta] per frame, then the GRU whose hidden state is C_dyn.
        motion_encoder = mlp([config.motion_dim + scfg.shape_dim, config.motion_hidden_dim, d])
        gru = nn.GRU(d, d, batch_first=True)
        blocks = nn.ModuleList(
            CrossAttentionBlock(d, scfg.num_heads, scfg.ffn_dim, scfg.dropout)
            for _ in range(config.num_static_dynamic_layers)
        )
        self.motion_encoder = motion_encoder.to(dtype=dtype, device=device)
        self.gru = gru.to(dtype=dtype, device=device)
        if config.fusion == FUSION_LAYERNORM_CONCAT:
            self.static_dynamic_blocks = nn.ModuleList()
            self.norm_static = nn.LayerNorm(d).to(dtype=dtype, device=device)
            self.norm_dynamic = nn.LayerNorm(d).to(dtype=dtype, device=device)
            self.head = _concat_head_from(static.head, d)
        else:
            self.static_dynamic_blocks = blocks.to(dtype=dtype, device=device)
            if config.fusion == FUSION_LORA:
                self.head = with_lora(static.head, config.lora_rank, config.lora_alpha)
            else:
                # Section 4.2.2: the dynamic head starts from the static head's parameters.
                self.head = _copy_head(static.head)

        static.requires_grad_(False)
        static.eval()
        self.static = static

    @classmethod
    def from_static(cls, static: StaticNetwork, config: DynamicConfig | None = None) -> DynamicNetwork:
        """A dynamic network around a pre-trained static one (Section 4.2.2).

        Args:
            static: the trained static network; frozen in place and kept by reference.
            config: dynamic settings; its `static` field is replaced by `static.config`.
                None: `DynamicConfig()` defaults around `static.config`.

        Returns:
            The dynamic network; its head equals the static head (same outputs on the same
            features) and `functional_regularization` is zero.
        """
        if not isinstance(static, StaticNetwork):
            raise ValueError(f"static: expected a StaticNetwork, got {type(static).__name__}")
        config = config if config is not None else DynamicConfig(static=static.config)
        if not isinstance(config, DynamicConfig):
            raise ValueError(f"config: expected a DynamicConfig, got {type(config).__name__}")
        return cls(dataclasses.replace(config, static=static.config), static)

    def train(self, mode: bool = True) -> DynamicNetwork:
        """Set train/eval mode; the frozen static network always stays in eval mode."""
        super().train(mode)
        self.static.eval()
        return self

    def trainable_parameters(self) -> list[nn.Parameter]:
        """The parameters an optimizer should update (everything but the frozen static network
        and, for the LoRA variant, the frozen base head).
        """
        return [p for p in self.parameters() if p.requires_grad]

    @property
    def uses_functional_regularization(self) -> bool:
        """False for the LoRA ablation, which replaces Eq. 4 by LoRA adapters."""
        return self.config.fusion != FUSION_LORA

    # -- pieces (unchecked) -----------------------------------------------------------------------
    def _static_features(self, z, beta, theta, contact=None):
        with torch.no_grad():
            return self.static._features(z, beta, theta, contact)

    def _check_contact(self, contact, batch, frames=None):
        """Check a contact-feature input: (B, L, F), or (B, T, L, F) with `frames`."""
        scfg = self.config.static
        if scfg.contact_samples == 0:
            if contact is not None:
                raise ValueError("contact: this network reads no contact features (contact_samples = 0)")
            return
        if contact is None:
            raise ValueError("contact: this network reads contact features (contact_samples > 0); pass "
                             "contact=network.contact_features(rigid, root_uv, body)")
        trailing = [scfg.num_cells, self.static.contact_dim]
        check_batch(self, batch, contact=(contact, trailing if frames is None else [frames, *trailing]))

    def contact_features(self, rigid: torch.Tensor, root_uv: torch.Tensor, body) -> torch.Tensor | None:
        """The contact features of frames (B, L, F), as the static network inside reads them (None: none)."""
        return self.static.contact_features(rigid, root_uv, body)

    def frame_contact_features(self, rigid: torch.Tensor, root_uv: torch.Tensor, body, batch: int):
        """`contact_features` of B sequences of T frames held as (B * T, M, N, 3), as (B, T, L, F)."""
        contact = self.contact_features(rigid, root_uv, body)
        return None if contact is None else contact.reshape(batch, -1, *contact.shape[1:])

    def _encode_motion(self, motion, beta, hidden):
        frames = torch.cat([motion, beta[:, None, :].expand(-1, motion.shape[1], -1)], dim=-1)
        _, last = self.gru(self.motion_encoder(frames), hidden[None])
        return last[0]

    def _fuse(self, static_features, c_dyn):
        context = c_dyn[:, None, :]
        if self.config.fusion == FUSION_LAYERNORM_CONCAT:
            h = self.norm_static(static_features)
            c = self.norm_dynamic(context).expand(-1, h.shape[1], -1)
            return torch.cat([h, c], dim=-1)
        x = static_features
        for block in self.static_dynamic_blocks:
            x = block(x, context)
        return x

    def _predict(self, fused, clip):
        scfg = self.config.static
        flat = clip_deformation(self.head(fused), clip)
        return reshape_map(flat, scfg.grid_height, scfg.grid_width, scfg.num_vertices)

    def _zero_hidden(self, batch, like):
        return torch.zeros(batch, self.config.static.model_dim, dtype=like.dtype, device=like.device)

    def _check_hidden(self, hidden, batch):
        if hidden is None:
            return None
        return check_batch(self, batch, hidden=(hidden, [self.config.static.model_dim]))

    # -- public -----------------------------------------------------------------------------------
    def encode_motion(
        self, motion: torch.Tensor, beta: torch.Tensor, hidden: torch.Tensor | None = None
    ) -> torch.Tensor:
        """C_dyn(t) = D_dyn(C_dyn(t-1), M(t)) (Section 3.3.1).

        Args:
            motion: (B, T_w, D) motion descriptors of the window ending at frame t.
            beta: (B, 16) body shapes.
            hidden: (B, d_m) C_dyn(t-1); None starts from zeros.

        Returns:
            (B, d_m) C_dyn(t).
        """
        cfg = self.config
        batch = check_batch(
            self, motion=(motion, [cfg.window, cfg.motion_dim]), beta=(beta, [cfg.static.shape_dim])
        )
        self._check_hidden(hidden, batch)
        hidden = self._zero_hidden(batch, motion) if hidden is None else hidden
        return self._encode_motion(motion, beta, hidden)

    def dynamic_head(self, features: torch.Tensor) -> torch.Tensor:
        """F_pred_dyn applied to static features as Eq. 4 reads it: (B, ..., d_m) -> (B, ..., N * 3).

        For "layernorm_concat" the head sees [LayerNorm(features), 0]: no dynamic context.
        """
        if self.config.fusion == FUSION_LAYERNORM_CONCAT:
            h = self.norm_static(features)
            return self.head(torch.cat([h, torch.zeros_like(h)], dim=-1))
        return self.head(features)

    def head_drift(self, static_features: torch.Tensor) -> torch.Tensor:
        """MSE(F_pred_dyn(H_static), F_pred_static(H_static)): Eq. 4 without its weight, for every
        variant (a diagnostic for LoRA, where it is not trained on).

        Args:
            static_features: (..., L, d_m) H_static, e.g. `DynamicOutput.static_features`.

        Returns:
            Scalar tensor [m^2], differentiable w.r.t. the dynamic head.
        """
        scfg = self.config.static
        dtype = next(self.head.parameters()).dtype
        device = next(self.head.parameters()).device
        check_tensor(
            "static_features", static_features, shape=["...", scfg.num_cells, scfg.model_dim],
            dtypes=(dtype,), device=device, allow_empty=False,
        )
        with torch.no_grad():
            target = self.static.head(static_features)
        return torch.mean((self.dynamic_head(static_features) - target) ** 2)

    def functional_regularization(self, static_features: torch.Tensor) -> torch.Tensor:
        """L_func_reg of Eq. 4: lambda_fr * MSE(F_pred_dyn(H_static), F_pred_static(H_static)).

        Zero at initialisation for "cross_attention" (the dynamic head is a copy of the static
        head); identically zero for "lora", which uses adapters instead.

        Args:
            static_features: (..., L, d_m) H_static, e.g. `DynamicOutput.static_features`.

        Returns:
            Scalar tensor [m^2] (lambda_fr = `config.func_reg_weight`), differentiable w.r.t.
            the dynamic head; the static head is frozen.
        """
        drift = self.head_drift(static_features)
        if not self.uses_functional_regularization:
            return drift.detach() * 0.0
        return self.config.func_reg_weight * drift

    def forward(
        self,
        z: torch.Tensor,
        beta: torch.Tensor,
        theta: torch.Tensor,
        motion: torch.Tensor,
        hidden: torch.Tensor | None = None,
        clip: float | None = None,
        contact: torch.Tensor | None = None,
    ) -> DynamicOutput:
        """One time step: D_dyn(t) and C_dyn(t) from frame t's pose and motion window.

        Args:
            z: (B, d_z) hair latents.
            beta: (B, 16) body shapes.
            theta: (B, 66) pose of frame t, axis-angle [rad].
            motion: (B, T_w, D) motion descriptors of the window ending at frame t.
            hidden: (B, d_m) C_dyn(t-1) from the previous step; None: zeros (first frame).
            clip: optional clamp of each deformation component [m].
            contact: (B, L, F) frame t's contact features, for a static network that reads them.

        Returns:
            DynamicOutput(deformation_map (B, M_H0, M_W0, N, 3) [m], hidden (B, d_m),
            static_features (B, L, d_m)).

        Raises:
            ValueError: naming the argument of wrong shape, dtype, device, or with NaN/Inf.
        """
        cfg = self.config
        scfg = cfg.static
        batch = check_batch(
            self, z=(z, [scfg.latent_dim]), beta=(beta, [scfg.shape_dim]), theta=(theta, [scfg.pose_dim]),
            motion=(motion, [cfg.window, cfg.motion_dim]),
        )
        self._check_hidden(hidden, batch)
        self._check_contact(contact, batch)
        hidden = self._zero_hidden(batch, z) if hidden is None else hidden
        static_features = self._static_features(z, beta, theta, contact)
        c_dyn = self._encode_motion(motion, beta, hidden)
        deformation = self._predict(self._fuse(static_features, c_dyn), clip)
        return DynamicOutput(deformation, c_dyn, static_features)

    def simulate(
        self,
        z: torch.Tensor,
        beta: torch.Tensor,
        poses: torch.Tensor,
        motion: torch.Tensor,
        hidden: torch.Tensor | None = None,
        clip: float | None = None,
        contact: torch.Tensor | None = None,
    ) -> DynamicOutput:
        """Run a whole sequence frame by frame, carrying C_dyn through the GRU, batched.

        The GRU steps run in order; the static features, cross-attention and head of all frames
        are then evaluated in one batch (they do not depend on each other across frames).
        Gradients flow back through time via the hidden state.

        Args:
            z: (B, d_z) hair latents (one hairstyle per sequence).
            beta: (B, 16) body shapes.
            poses: (B, T, 66) pose of each frame, axis-angle [rad].
            motion: (B, T, T_w, D) the motion-descriptor window ending at each frame.
            hidden: (B, d_m) C_dyn before the first frame; None: zeros.
            clip: optional clamp of each deformation component [m].
            contact: (B, T, L, F) contact features of each frame, for a static network that
                reads them (`frame_contact_features`).

        Returns:
            DynamicOutput(deformation_map (B, T, M_H0, M_W0, N, 3) [m], hidden (B, d_m) after
            the last frame, static_features (B, T, L, d_m)).
        """
        cfg = self.config
        scfg = cfg.static
        batch = check_batch(
            self, z=(z, [scfg.latent_dim]), beta=(beta, [scfg.shape_dim]),
            poses=(poses, [None, scfg.pose_dim]), motion=(motion, [None, cfg.window, cfg.motion_dim]),
        )
        frames = poses.shape[1]
        if frames == 0:
            raise ValueError("poses: expected at least one frame, got 0")
        if motion.shape[1] != frames:
            raise ValueError(f"motion: expected {frames} frames like poses, got {motion.shape[1]}")
        self._check_hidden(hidden, batch)
        self._check_contact(contact, batch, frames)
        hidden = self._zero_hidden(batch, z) if hidden is None else hidden

        codes = []
        for t in range(frames):
            hidden = self._encode_motion(motion[:, t], beta, hidden)
            codes.append(hidden)
        c_dyn = torch.stack(codes, dim=1).reshape(batch * frames, -1)

        def per_frame(x):
            return x[:, None].expand(batch, frames, *x.shape[1:]).reshape(batch * frames, *x.shape[1:])

        flat_contact = None if contact is None else contact.reshape(batch * frames, *contact.shape[2:])
        static_features = self._static_features(per_frame(z), per_frame(beta), poses.reshape(batch * frames, -1),
                                                flat_contact)
        deformation = self._predict(self._fuse(static_features, c_dyn), clip)
        return DynamicOutput(
            deformation.reshape(batch, frames, *deformation.shape[1:]),
            hidden,
            static_features.reshape(batch, frames, *static_features.shape[1:]),
        )

    def drape(
        self,
        z: torch.Tensor,
        beta: torch.Tensor,
        theta: torch.Tensor,
        motion: torch.Tensor,
        rigid: torch.Tensor,
        root_uv: torch.Tensor,
        hidden: torch.Tensor | None = None,
        clip: float | None = None,
        contact: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One step's hair positions (Eq. 2 with D_dyn) and the next hidden state.

        Args:
            z, beta, theta, motion, hidden, clip, contact: as in `forward`.
            rigid: (B, M, N, 3) rigidly posed hair of frame t [m].
            root_uv: (M, 2) or (B, M, 2) root UVs in [0, 1]^2.

        Returns:
            ((B, M, N, 3) positions [m], (B, d_m) C_dyn(t)).
        """
        out = self.forward(z, beta, theta, motion, hidden, clip, contact)
        return apply_deformation(rigid, out.deformation_map, root_uv, self.config.static.length_projection), out.hidden


def _copy_head(head: PredictionHead) -> PredictionHead:
    copied = copy.deepcopy(head)
    copied.requires_grad_(True)
    return copied
