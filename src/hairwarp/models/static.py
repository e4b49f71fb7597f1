"""The static Hair Transformer (HairFormer Section 3.2, Eq. 3).

H_ctx = E_hair(z), C_body = E_body([beta, Theta]), H_static = I_hb*(H_ctx, C_body),
D_static = Reshape(F_pred_static(H_static)): a deformation map (B, M_H0, M_W0, N, 3) that
`hairwarp.models.deformation.apply_deformation` adds to the rigidly placed hair (Eq. 2).
"""

from __future__ import annotations

import torch
from torch import nn

from hairwarp.models.config import StaticConfig
from hairwarp.models.contact_features import FEATURES_PER_SAMPLE, contact_features
from hairwarp.models.deformation import apply_deformation
from hairwarp.models.layers import (
    CrossAttentionBlock,
    PredictionHead,
    check_batch,
    clip_deformation,
    mlp,
    reshape_map,
    sinusoidal_encoding_2d,
)
from hairwarp.scene.motion import standing_pose
from hairwarp.scene.skeleton import JOINT
from hairwarp._validate import check_tensor


class HairEncoder(nn.Module):
    """E_hair (Section 3.2.1): L learnable queries + 2D positional encoding, and z as one token.

    The (L + 1) tokens [queries + PE, proj(z)] pass N_enc self-attention layers; the z token is
    dropped and the L others are H_ctx.
    """

    def __init__(self, cfg: StaticConfig):
        super().__init__()
        d = cfg.model_dim
        self.queries = nn.Parameter(torch.randn(cfg.num_cells, d) * 0.02)
        # Fixed, so not stored in checkpoints: rebuilt from the config.
        self.register_buffer(
            "position", sinusoidal_encoding_2d(cfg.grid_height, cfg.grid_width, d), persistent=False
        )
        self.latent_projection = nn.Linear(cfg.latent_dim, d)
        layer = nn.TransformerEncoderLayer(
            d, cfg.num_heads, cfg.ffn_dim, cfg.dropout, activation="gelu", batch_first=True
        )
        self.encoder = nn.TransformerEncoder(layer, cfg.num_encoder_layers, enable_nested_tensor=False)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """Z (B, d_z) -> H_ctx (B, L, d_m)."""
        batch = z.shape[0]
        queries = (self.queries + self.position.to(self.queries.dtype)).expand(batch, -1, -1)
        tokens = torch.cat([queries, self.latent_projection(z)[:, None, :]], dim=1)
        return self.encoder(tokens)[:, :-1, :]


class StaticNetwork(nn.Module):
    """Static Hair Transformer: (z, beta, Theta) -> deformation map D_static (Eq. 3).

    Args:
        config: sizes; `StaticConfig()` is the paper's (d_m = 512, 8x8 grid, N = 100).

    Attributes:
        config: the StaticConfig the network was built from (checkpoints store it).
        hair_encoder: E_hair.
        body_encoder: E_body, an MLP [beta, Theta] -> one d_m token.
        hair_body_blocks: I_hb, N_hb cross-attention + FFN blocks.
        head: F_pred_static.
    """

    kind = "static"

    def __init__(self, config: StaticConfig | None = None):
        super().__init__()
        cfg = config if config is not None else StaticConfig()
        if not isinstance(cfg, StaticConfig):
            raise ValueError(f"config: expected a StaticConfig, got {type(cfg).__name__}")
        self.config = cfg
        d = cfg.model_dim
        self.hair_encoder = HairEncoder(cfg)
        self.body_encoder = mlp([cfg.shape_dim + cfg.pose_dim, cfg.body_hidden_dim, d])
        self.hair_body_blocks = nn.ModuleList(
            CrossAttentionBlock(d, cfg.num_heads, cfg.ffn_dim, cfg.dropout) for _ in range(cfg.num_hair_body_layers)
        )
        self.head = PredictionHead(d, cfg.head_hidden_dim, cfg.head_layers, cfg.num_vertices, cfg.head_init_gain)
        # Beyond the paper (config.contact_samples > 0): each hair token also reads its cell's
        # rigid placement against the body, so the network need not infer contact from the pose.
        self.contact_encoder = (mlp([cfg.contact_samples * FEATURES_PER_SAMPLE, d, d])
                                if cfg.contact_samples > 0 else None)
        # config.held_joints: their columns of Theta and the standing pose's values there.
        columns = torch.tensor([3 * JOINT[j] + k for j in cfg.held_joints for k in range(3)], dtype=torch.long)
        self.register_buffer("held_columns", columns, persistent=False)
        self.register_buffer("held_angles", standing_pose()[columns], persistent=False)

    @property
    def contact_dim(self) -> int:
        """Numbers per cell of the contact features this network reads (0: none, the paper)."""
        return self.config.contact_samples * FEATURES_PER_SAMPLE

    def contact_features(self, rigid: torch.Tensor, root_uv: torch.Tensor, body) -> torch.Tensor | None:
        """The contact features of a batch (None for the paper's network, which reads none).

        Args:
            rigid: (B, M, N, 3) rigidly placed hair [m]; root_uv: (M, 2) or (B, M, 2).
            body: the posed `hairwarp.ops.BodyMesh` (batch 1 or B).

        Returns:
            (B, L, contact_dim) in the network's dtype, or None.
        """
        cfg = self.config
        if cfg.contact_samples == 0:
            return None
        dtype = next(self.parameters()).dtype
        return contact_features(rigid, root_uv, body, cfg.grid_height, cfg.grid_width, cfg.contact_samples).to(dtype)

    # -- pieces (unchecked; the public methods check their inputs once) -------------------------
    def _features(self, z, beta, theta, contact=None):
        hair = self.hair_encoder(z)
        if self.contact_encoder is not None:
            hair = hair + self.contact_encoder(contact)
        if self.held_columns.numel():
            theta = theta.index_copy(1, self.held_columns, self.held_angles.to(theta.dtype).expand(theta.shape[0], -1))
        body = self.body_encoder(torch.cat([beta, theta], dim=-1))[:, None, :]
        for block in self.hair_body_blocks:
            hair = block(hair, body)
        return hair

    def _predict(self, features, clip):
        cfg = self.config
        flat = clip_deformation(self.head(features), clip)
        return reshape_map(flat, cfg.grid_height, cfg.grid_width, cfg.num_vertices)

    def _check(self, z, beta, theta, contact=None) -> int:
        cfg = self.config
        inputs = {"z": (z, [cfg.latent_dim]), "beta": (beta, [cfg.shape_dim]), "theta": (theta, [cfg.pose_dim])}
        if self.contact_encoder is not None:
            if contact is None:
                raise ValueError("contact: this network reads contact features (config.contact_samples > 0); "
                                 "pass contact=network.contact_features(rigid, root_uv, body)")
            inputs["contact"] = (contact, [cfg.num_cells, self.contact_dim])
        elif contact is not None:
            raise ValueError("contact: this network reads no contact features (config.contact_samples = 0)")
        return check_batch(self, **inputs)

    # -- public -----------------------------------------------------------------------------------
    def features(self, z: torch.Tensor, beta: torch.Tensor, theta: torch.Tensor,
                 contact: torch.Tensor | None = None) -> torch.Tensor:
        """Body-aware hair tokens H_static = I_hb*(E_hair(z), E_body([beta, Theta])).

        Args:
            z: (B, d_z) hair latents.
            beta: (B, 16) body shapes.
            theta: (B, 66) body poses, axis-angle [rad] (22 SMPL joints).
            contact: (B, L, contact_dim) from `contact_features`, for a network that reads them.

        Returns:
            (B, L, d_m) features, L = M_H0 * M_W0, token l = row * M_W0 + col.

        Raises:
            ValueError: naming the argument of wrong shape, dtype, device, or with NaN/Inf.
        """
        self._check(z, beta, theta, contact)
        return self._features(z, beta, theta, contact)

    def predict(self, features: torch.Tensor, clip: float | None = None) -> torch.Tensor:
        """F_pred_static and the reshape of Eq. 3: features (B, L, d_m) -> (B, M_H0, M_W0, N, 3) [m].

        Args:
            features: H_static from `features`.
            clip: clamp each component to [-clip, clip] [m] (the paper clips at 0.01 early in
                training: `config.deformation_clip`); None leaves it unclipped.
        """
        cfg = self.config
        check_batch(self, features=(features, [cfg.num_cells, cfg.model_dim]))
        return self._predict(features, clip)

    def forward(
        self, z: torch.Tensor, beta: torch.Tensor, theta: torch.Tensor, clip: float | None = None,
        contact: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The deformation map D_static(z, beta, Theta) of Eq. 3.

        Args:
            z: (B, d_z) hair latents.
            beta: (B, 16) body shapes.
            theta: (B, 66) body poses, axis-angle [rad].
            clip: optional clamp of each deformation component [m] (see `predict`).
            contact: (B, L, contact_dim) from `contact_features` (networks that read them only).

        Returns:
            (B, M_H0, M_W0, N, 3) deformations [m] in the network's dtype, on its device.

        Raises:
            ValueError: naming the argument of wrong shape, dtype, device, or with NaN/Inf.
        """
        self._check(z, beta, theta, contact)
        return self._predict(self._features(z, beta, theta, contact), clip)

    def drape(
        self,
        z: torch.Tensor,
        beta: torch.Tensor,
        theta: torch.Tensor,
        rigid: torch.Tensor,
        root_uv: torch.Tensor,
        clip: float | None = None,
        contact: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Static hair positions P_static of Eq. 2: rigid + tapered nearest-cell deformations
        (projected onto the rest lengths when `config.length_projection` asks for it).

        Args:
            z, beta, theta: as in `forward`.
            rigid: (B, M, N, 3) rigidly posed hair [m] (Eq. 1).
            root_uv: (M, 2) or (B, M, 2) root UVs in [0, 1]^2.
            clip: as in `forward`.
            contact: as in `forward`.

        Returns:
            (B, M, N, 3) positions [m]; vertices 0 and 1 equal `rigid` exactly.
        """
        check_tensor("rigid", rigid, shape=[None, None, self.config.num_vertices, 3], dtypes=None)
        deformation = self.forward(z, beta, theta, clip, contact)
        return apply_deformation(rigid, deformation, root_uv, self.config.length_projection)
