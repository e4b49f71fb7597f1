"""The Quaffure (adapted) baseline: a convolutional groom-deformation decoder (Section 4.3.1).

[z, beta, Theta] -> Linear -> 512 x 4 x 4 -> three stride-2 transposed convolutions ->
64 x 32 x 32 -> Conv2d -> (N * 3) x 32 x 32: a deformation map on the full 32x32 scalp grid,
read per strand at its root-UV cell and tapered like HairFormer's (Section 4.2.3) by
`hairwarp.models.deformation.apply_deformation`.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from hairwarp._validate import check_tensor
from hairwarp.models.config import QuaffureConfig
from hairwarp.models.deformation import apply_deformation
from hairwarp.models.layers import check_batch, clip_deformation


class QuaffureNetwork(nn.Module):
    """Quaffure (adapted): (z, beta, Theta) -> deformation map (B, 32, 32, N, 3).

    Stuyck et al. (2024) do not fix the activations of their decoder for our latent input;
    we use LeakyReLU(0.2) between layers, as in convolutional decoders of that family, and a
    3x3 output convolution whose weights start small (millimetre deformations), like the
    HairFormer head.

    Args:
        config: sizes; `QuaffureConfig()` is the paper's.

    Attributes:
        config: the QuaffureConfig the network was built from.
    """

    kind = "quaffure"

    def __init__(self, config: QuaffureConfig | None = None):
        super().__init__()
        cfg = config if config is not None else QuaffureConfig()
        if not isinstance(cfg, QuaffureConfig):
            raise ValueError(f"config: expected a QuaffureConfig, got {type(cfg).__name__}")
        self.config = cfg
        c0, c1, c2, c3 = cfg.channels
        self.input = nn.Linear(cfg.latent_dim + cfg.shape_dim + cfg.pose_dim, c0 * cfg.base_size**2)
        self.upsample = nn.Sequential(
            nn.LeakyReLU(0.2),
            # kernel 4, stride 2, padding 1 doubles the side exactly: 4 -> 8 -> 16 -> 32.
            nn.ConvTranspose2d(c0, c1, 4, stride=2, padding=1),
            nn.LeakyReLU(0.2),
            nn.ConvTranspose2d(c1, c2, 4, stride=2, padding=1),
            nn.LeakyReLU(0.2),
            nn.ConvTranspose2d(c2, c3, 4, stride=2, padding=1),
            nn.LeakyReLU(0.2),
        )
        self.output = nn.Conv2d(c3, cfg.num_vertices * 3, 3, padding=1)
        bound = cfg.head_init_gain / math.sqrt(c3 * 9)
        with torch.no_grad():
            self.output.weight.uniform_(-bound, bound)
            self.output.bias.zero_()

    def forward(
        self, z: torch.Tensor, beta: torch.Tensor, theta: torch.Tensor, clip: float | None = None
    ) -> torch.Tensor:
        """The deformation map on the 32x32 scalp grid.

        Args:
            z: (B, d_z) hair latents.
            beta: (B, 16) body shapes.
            theta: (B, 66) body poses, axis-angle [rad].
            clip: optional clamp of each deformation component [m].

        Returns:
            (B, S, S, N, 3) deformations [m], S = 32 (rows follow root v, columns root u).

        Raises:
            ValueError: naming the argument of wrong shape, dtype, device, or with NaN/Inf.
        """
        cfg = self.config
        batch = check_batch(
            self, z=(z, [cfg.latent_dim]), beta=(beta, [cfg.shape_dim]), theta=(theta, [cfg.pose_dim])
        )
        x = self.input(torch.cat([z, beta, theta], dim=-1))
        x = self.upsample(x.reshape(batch, cfg.channels[0], cfg.base_size, cfg.base_size))
        x = clip_deformation(self.output(x), clip)  # (B, N * 3, S, S)
        side = cfg.grid_size
        return x.permute(0, 2, 3, 1).reshape(batch, side, side, cfg.num_vertices, 3)

    def drape(
        self,
        z: torch.Tensor,
        beta: torch.Tensor,
        theta: torch.Tensor,
        rigid: torch.Tensor,
        root_uv: torch.Tensor,
        clip: float | None = None,
    ) -> torch.Tensor:
        """Hair positions: rigid + tapered deformation of each strand's 32x32 cell.

        Args:
            z, beta, theta, clip: as in `forward`.
            rigid: (B, M, N, 3) rigidly posed hair [m].
            root_uv: (M, 2) or (B, M, 2) root UVs in [0, 1]^2.

        Returns:
            (B, M, N, 3) positions [m]; vertices 0 and 1 equal `rigid` exactly.
        """
        check_tensor("rigid", rigid, shape=[None, None, self.config.num_vertices, 3], dtypes=None)
        return apply_deformation(rigid, self.forward(z, beta, theta, clip), root_uv, self.config.length_projection)
