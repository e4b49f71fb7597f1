"""Building blocks shared by the HairFormer networks (Sections 3.2-3.3, 4.5.2).

The 2D sinusoidal positional encoding of the hair queries, the cross-attention block used by
both I_hb (hair-body) and I_sd (static-dynamic), the MLP prediction head F_pred, LoRA adapters
(the Section 4.5.2 ablation) and the input checks every network's public methods share.
"""

from __future__ import annotations

import copy
import math

import torch
from torch import nn

from hairwarp._validate import check_tensor


def sinusoidal_encoding_2d(height: int, width: int, dim: int) -> torch.Tensor:
    """Fixed 2D sinusoidal positional encoding of a height x width grid (Section 3.2.1).

    The first dim/2 channels encode the row, the last dim/2 the column, each as interleaved-free
    [sin, cos] halves over geometrically spaced frequencies (Vaswani et al.'s 1D encoding per
    axis). Token l = row * width + col, the order of the deformation map's cells.

    Args:
        height: grid rows (M_H0).
        width: grid columns (M_W0).
        dim: channels, a multiple of 4.

    Returns:
        (height * width, dim) float32 tensor, values in [-1, 1].
    """
    if dim % 4:
        raise ValueError(f"dim: expected a multiple of 4, got {dim}")
    quarter = dim // 4
    freq = torch.exp(-math.log(10000.0) * torch.arange(quarter, dtype=torch.float64) / quarter)
    rows = torch.arange(height, dtype=torch.float64)[:, None] * freq  # (H, dim/4)
    cols = torch.arange(width, dtype=torch.float64)[:, None] * freq  # (W, dim/4)
    row_enc = torch.cat([rows.sin(), rows.cos()], dim=1)  # (H, dim/2)
    col_enc = torch.cat([cols.sin(), cols.cos()], dim=1)  # (W, dim/2)
    enc = torch.cat(
        [row_enc[:, None, :].expand(height, width, -1), col_enc[None, :, :].expand(height, width, -1)], dim=2
    )
    return enc.reshape(height * width, dim).float()


def mlp(sizes: list[int], *, activation=nn.GELU) -> nn.Sequential:
    """Linear layers of the given sizes with `activation` between them (none after the last)."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(activation())
    return nn.Sequential(*layers)


class CrossAttentionBlock(nn.Module):
    """Multi-head cross-attention then a position-wise FFN, each residual + LayerNorm.

    One block of I_hb (Section 3.2.3: hair queries, body key/value) or I_sd (Section 3.3.2:
    static hair queries, dynamic key/value). With a single context token, softmax over one key
    is 1: every query receives the same projected context, added through the residual; the
    queries then differ only through their own FFN path. That is the paper's design (C_body and
    C_dyn are one token each).

    Args:
        dim: d_m.
        num_heads: attention heads.
        ffn_dim: FFN hidden width.
        dropout: dropout probability on attention weights and residual branches.
    """

    def __init__(self, dim: int, num_heads: int, ffn_dim: int, dropout: float = 0.0):
        super().__init__()
        self.attention = nn.MultiheadAttention(dim, num_heads, dropout=dropout, batch_first=True)
        self.norm_attention = nn.LayerNorm(dim)
        self.ffn = nn.Sequential(nn.Linear(dim, ffn_dim), nn.GELU(), nn.Dropout(dropout), nn.Linear(ffn_dim, dim))
        self.norm_ffn = nn.LayerNorm(dim)
        self.dropout = nn.Dropout(dropout)

    def forward(self, queries: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        """Queries (B, L, d_m), context (B, K, d_m) -> (B, L, d_m)."""
        attended, _ = self.attention(queries, context, context, need_weights=False)
        x = self.norm_attention(queries + self.dropout(attended))
        return self.norm_ffn(x + self.dropout(self.ffn(x)))


class PredictionHead(nn.Module):
    """F_pred: an MLP from hair tokens to per-cell strand deformations (Sections 3.2.4, 3.3.3).

    Maps (B, L, in_dim) to (B, L, N * 3); `reshape_map` turns that into the deformation map
    (B, M_H0, M_W0, N, 3). The last layer starts small (uniform +-gain/sqrt(fan_in), zero bias)
    so the initial deformations are about `gain` metres, well inside the paper's 0.01 clip.

    Args:
        in_dim: token width (d_m; 2 d_m for the LayerNorm-concat ablation).
        hidden_dim: hidden width.
        num_layers: linear layers (>= 1).
        num_vertices: N.
        init_gain: scale of the last layer's initial weights.
    """

    def __init__(self, in_dim: int, hidden_dim: int, num_layers: int, num_vertices: int, init_gain: float):
        super().__init__()
        sizes = [in_dim] + [hidden_dim] * (num_layers - 1) + [num_vertices * 3]
        self.net = mlp(sizes)
        last = self.net[-1]
        bound = init_gain / math.sqrt(last.in_features)
        with torch.no_grad():
            last.weight.uniform_(-bound, bound)
            last.bias.zero_()

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        """Tokens (B, L, in_dim) -> raw deformations (B, L, N * 3) [m]."""
        return self.net(tokens)


def reshape_map(flat: torch.Tensor, grid_height: int, grid_width: int, num_vertices: int) -> torch.Tensor:
    """(B, L, N * 3) head output -> (B, M_H0, M_W0, N, 3) deformation map (token l = row * W + col)."""
    return flat.reshape(flat.shape[0], grid_height, grid_width, num_vertices, 3)


def clip_deformation(deformation: torch.Tensor, clip: float | None) -> torch.Tensor:
    """Clamp each deformation component to [-clip, clip] [m] (Section 4.2.1); None: unchanged."""
    if clip is None:
        return deformation
    clip = float(clip)
    if not clip > 0 or clip == float("inf"):
        raise ValueError(f"clip: expected a positive finite number or None, got {clip}")
    return deformation.clamp(-clip, clip)


class LoRALinear(nn.Module):
    """A frozen linear layer plus a trainable low-rank update (Hu et al. 2022; Section 4.5.2).

    y = base(x) + (alpha / rank) * up(down(x)); `up` starts at zero so the layer starts equal
    to `base`; `down` starts like a default nn.Linear (Kaiming uniform).

    Args:
        base: the linear layer to adapt; it is deep-copied and frozen.
        rank: adapter rank r.
        alpha: LoRA alpha.
    """

    def __init__(self, base: nn.Linear, rank: int, alpha: float):
        super().__init__()
        self.base = copy.deepcopy(base)
        self.base.requires_grad_(False)
        param = base.weight
        self.down = nn.Linear(base.in_features, rank, bias=False, device=param.device, dtype=param.dtype)
        self.up = nn.Linear(rank, base.out_features, bias=False, device=param.device, dtype=param.dtype)
        nn.init.zeros_(self.up.weight)
        self.scaling = float(alpha) / float(rank)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.base(x) + self.scaling * self.up(self.down(x))


def with_lora(head: PredictionHead, rank: int, alpha: float) -> PredictionHead:
    """A copy of `head` whose linear layers are frozen and carry LoRA adapters."""
    adapted = copy.deepcopy(head)
    for i, layer in enumerate(adapted.net):
        if isinstance(layer, nn.Linear):
            adapted.net[i] = LoRALinear(layer, rank, alpha)
    return adapted


def module_dtype_device(module: nn.Module) -> tuple[torch.dtype, torch.device]:
    """The dtype and device of a network's parameters (all share them)."""
    p = next(module.parameters())
    return p.dtype, p.device


def check_batch(module: nn.Module, batch: int | None = None, **tensors) -> int:
    """Validate a network's batched inputs; return the batch size.

    Each keyword is `name=(tensor, trailing_shape)`: the tensor must be (B, *trailing_shape),
    finite, of the network's dtype and on its device, with one B across all of them.

    Raises:
        ValueError: naming the offending argument.
    """
    dtype, device = module_dtype_device(module)
    for name, (t, trailing) in tensors.items():
        check_tensor(name, t, shape=[None, *trailing], dtypes=(dtype,), device=device, allow_empty=False)
        if batch is None:
            batch = int(t.shape[0])
        elif t.shape[0] != batch:
            raise ValueError(f"{name}: expected batch size {batch} like the other inputs, got {t.shape[0]}")
    return batch
