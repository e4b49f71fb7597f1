"""The 512-d hair latent z (Section 3.1): a linear basis over hairstyles on the scalp grid.

The paper decodes z with PERM's StyleGAN; we fit a linear model on a corpus of procedural
hairstyles instead, in the spirit of PERM's strand PCA, so z in R^512 means the same thing to
every part of the pipeline (the hair encoder of Section 3.2.1 takes it) and loaded hairstyles
can be encoded too.

Representation (all linear, so `encode` is an exact least-squares fit of `decode`):
  1. Strand basis: each strand's offsets from its root, x_s in R^(N x 3) (N = 100), are
     projected onto K = 32 principal strand shapes V (300 x K, orthonormal, fitted on the
     uncentred strands, so the mean hairstyle is in its span): c_s = V^T x_s.
  2. Spatial basis: the coefficient maps over the 32 x 32 grid, minus the corpus mean map,
     are expanded on the leading principal spatial modes U (1024 x A, orthonormal). Strand
     channel k keeps its first A_k modes (more for the low-order channels that carry most of
     the shape: A = 320, 192, 96, 48 for channels 0-3, 4-7, 8-15, 16-31), a core of
     D = sum A_k = 3584 numbers per hairstyle.
  3. Latent: the top 512 principal components P (D x 512, orthonormal) of the cores, with
     z whitened by the corpus standard deviations sigma: core = P (sigma * z).
So decode(z) = roots + V^T-expansion of (mean map + U-expansion of P (sigma z)); z ~ N(0, I)
for the corpus. Stored as float16 (U, P) and float32 (the rest) in `assets/hair_basis.npz`
(4.2 MB); U and P are re-orthonormalised in float64 on load, so encode(decode(z)) = z holds
to rounding. `tools/fit_hair_basis.py` fits it on 1200 procedural styles of the synthetic
scalp and stores the measured reconstruction errors in `info` (mean vertex error of
decode(encode(s)): 3.6 mm on corpus styles, 5.4 mm on held-out styles of the family).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from dataclasses import dataclass
from importlib import resources

import numpy as np
import torch

from hairwarp._validate import check_tensor
from hairwarp.scene.scalp import Scalp

LATENT_DIM = 512
DEFAULT_STRAND_DIM = 32
# Spatial modes kept per strand channel (channel k of the strand PCA keeps the first A_k).
DEFAULT_SPATIAL_MODES = (320,) * 4 + (192,) * 4 + (96,) * 8 + (48,) * 16
DEFAULT_BASIS_FILE = "hair_basis.npz"


def _orthonormal(a: np.ndarray) -> np.ndarray:
    """Orthonormalise the columns of a nearly orthonormal matrix (float64), keeping them close.

    Cholesky QR, twice: Q = A L^-T with L L^T = A^T A. For A^T A ~ I (float16 storage) it is
    as accurate as Householder QR and ~20x faster for the (3584, 512) latent components.
    """
    q = a.astype(np.float64)
    for _ in range(2):
        chol = np.linalg.cholesky(q.T @ q)
        q = np.linalg.solve(chol, q.T).T
    return q


@dataclass(eq=False)
class HairLatentBasis:
    """A fitted linear hair latent (see the module docstring for the representation).

    Attributes:
        strand_basis: V, (N*3, K) float64, orthonormal columns.
        spatial_basis: U, (M, A_max) float64, orthonormal columns.
        spatial_modes: (K,) int64, A_k modes kept for strand channel k.
        mean_coefficients: (M, K) float64 mean strand-coefficient map.
        components: P, (D, L) float64 orthonormal columns, D = sum(A_k), L the latent size.
        sigma: (L,) float64 standard deviation of each latent coordinate over the corpus.
        roots: (M, 3) float32 grid root positions [m] of the scalp the basis was fitted on.
        root_uv: (M, 2) float32 grid root UVs.
        root_normals: (M, 3) float32 scalp normals at the roots.
        num_vertices: N, vertices per strand.
        info: fitting facts (corpus size, reconstruction errors [m], ...).
    """

    strand_basis: np.ndarray
    spatial_basis: np.ndarray
    spatial_modes: np.ndarray
    mean_coefficients: np.ndarray
    components: np.ndarray
    sigma: np.ndarray
    roots: np.ndarray
    root_uv: np.ndarray
    root_normals: np.ndarray
    num_vertices: int
    info: dict

    def __post_init__(self):
        k = self.strand_basis.shape[1]
        a = np.asarray(self.spatial_modes, dtype=np.int64)
        # Flat positions of the core's D numbers inside the (A_max, K) coefficient block,
        # channel by channel: decode scatters into it, encode gathers from it.
        self._core_index = np.concatenate([np.arange(a[c]) * k + c for c in range(k)])
        self._cache: dict = {}

    @property
    def latent_dim(self) -> int:
        return int(self.components.shape[1])

    @property
    def num_roots(self) -> int:
        return int(self.roots.shape[0])

    # ------------------------------------------------------------------ I/O

    @classmethod
    def load(cls, path: str | os.PathLike) -> HairLatentBasis:
        """Load a basis written by `save` (or `tools/fit_hair_basis.py`)."""
        name = os.fspath(path)
        try:
            with np.load(name, allow_pickle=False) as f:
                d = {k: f[k] for k in f.files}
        except (OSError, ValueError) as e:
            raise ValueError(f"{name}: not a readable hair basis ({e})") from e
        need = ("strand_basis", "spatial_basis", "spatial_modes", "mean_coefficients", "components",
                "sigma", "roots", "root_uv", "root_normals", "num_vertices", "info")
        missing = [k for k in need if k not in d]
        if missing:
            raise ValueError(f"{name}: missing key(s) {missing}")
        return cls(
            strand_basis=_orthonormal(d["strand_basis"]),
            spatial_basis=_orthonormal(d["spatial_basis"]),
            spatial_modes=d["spatial_modes"].astype(np.int64),
            mean_coefficients=d["mean_coefficients"].astype(np.float64),
            components=_orthonormal(d["components"]),
            sigma=d["sigma"].astype(np.float64),
            roots=d["roots"].astype(np.float32),
            root_uv=d["root_uv"].astype(np.float32),
            root_normals=d["root_normals"].astype(np.float32),
            num_vertices=int(d["num_vertices"]),
            info=json.loads(str(d["info"])),
        )

    @classmethod
    def load_default(cls) -> HairLatentBasis:
        """The basis shipped with the package (`hairwarp/assets/hair_basis.npz`), cached."""
        global _DEFAULT
        if _DEFAULT is None:
            ref = resources.files("hairwarp").joinpath("assets", DEFAULT_BASIS_FILE)
            with resources.as_file(ref) as path:
                _DEFAULT = cls.load(path)
        return _DEFAULT

    def save(self, path: str | os.PathLike) -> None:
        """Write the basis (U and P as float16, the rest float32), compressed."""
        np.savez_compressed(
            path,
            strand_basis=self.strand_basis.astype(np.float32),
            spatial_basis=self.spatial_basis.astype(np.float16),
            spatial_modes=np.asarray(self.spatial_modes, dtype=np.int32),
            mean_coefficients=self.mean_coefficients.astype(np.float32),
            components=self.components.astype(np.float16),
            sigma=self.sigma.astype(np.float32),
            roots=self.roots.astype(np.float32),
            root_uv=self.root_uv.astype(np.float32),
            root_normals=self.root_normals.astype(np.float32),
            num_vertices=np.int32(self.num_vertices),
            info=np.array(json.dumps(self.info)),
        )

    # ------------------------------------------------------------------ torch views

    def _tensors(self, device: torch.device, dtype: torch.dtype) -> dict:
        key = (str(device), dtype)
        if key not in self._cache:
            t = lambda a: torch.as_tensor(np.ascontiguousarray(a), device=device).to(dtype)  # noqa: E731
            self._cache[key] = {
                "V": t(self.strand_basis),
                "U": t(self.spatial_basis),
                "mean": t(self.mean_coefficients),
                "P": t(self.components),
                "sigma": t(self.sigma),
                "index": torch.as_tensor(self._core_index, device=device),
                "roots": t(self.roots),
            }
        return self._cache[key]

    # ------------------------------------------------------------------ decode / encode

    def decode(self, z: torch.Tensor, scalp: Scalp | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Hairstyles from latents: P_init = G_hair(z) (Section 3.1).

        Args:
            z: (B, L) or (L,) latents (L = 512), float32 or float64; z ~ N(0, I) spans the
                corpus family. Differentiable.
            scalp: optional scalp to attach the strands to; each grid root takes the scalp
                root with the nearest UV. Default: the roots the basis was fitted on.

        Returns:
            strands (B, M, N, 3) (or (M, N, 3) for 1-d z) [m] in z's dtype and device, vertex 0
            exactly at the roots; root_uv (M, 2) float32.
        """
        single = z.dim() == 1
        check_tensor("z", z, shape=("...", self.latent_dim))
        if z.dim() not in (1, 2):
            raise ValueError(
                f"z: expected shape (B, {self.latent_dim}) or ({self.latent_dim},), got {tuple(z.shape)}"
            )
        zb = z[None] if single else z
        b = zb.shape[0]
        t = self._tensors(zb.device, zb.dtype)
        m, k = self.mean_coefficients.shape
        a_max = self.spatial_basis.shape[1]
        core = (zb * t["sigma"]) @ t["P"].T  # (B, D)
        block = torch.zeros(b, a_max * k, dtype=zb.dtype, device=zb.device)
        block = block.index_copy(1, t["index"], core).reshape(b, a_max, k)
        coeff = t["mean"] + t["U"] @ block  # (B, M, K)
        offsets = (coeff @ t["V"].T).reshape(b, m, self.num_vertices, 3)
        roots = t["roots"] if scalp is None else self._scalp_roots(scalp, zb.device, zb.dtype)
        # The strand basis does not pin vertex 0 to exactly zero offset: set it.
        offsets = torch.cat([torch.zeros_like(offsets[:, :, :1]), offsets[:, :, 1:]], dim=2)
        strands = roots[None, :, None, :] + offsets
        uv = torch.as_tensor(self.root_uv, device=zb.device)
        return (strands[0] if single else strands), uv

    def encode(self, strands: torch.Tensor, root_uv: torch.Tensor | None = None) -> torch.Tensor:
        """Least-squares latent of a hairstyle: argmin_z |decode(z) - strands|^2.

        Strands are taken relative to their own roots (vertex 0). When `root_uv` is given, each
        grid root takes the strand whose root UV is nearest (so hairstyles with other roots or
        missing strands, e.g. loaded `.data` files, are resampled onto the grid first); without
        it the strands must be the M grid strands in grid order. Strands with a vertex count
        other than N are resampled by arc length.

        Args:
            strands: (S, n, 3) or (B, S, n, 3) strand positions [m].
            root_uv: (S, 2) root UVs in [0, 1]^2, or None.

        Returns:
            z: (L,) or (B, L), dtype and device of `strands`.
        """
        check_tensor("strands", strands, shape=("...", None, None, 3), allow_empty=False)
        if strands.dim() not in (3, 4):
            raise ValueError(f"strands: expected (S, n, 3) or (B, S, n, 3), got {tuple(strands.shape)}")
        single = strands.dim() == 3
        s = strands[None] if single else strands
        if s.shape[2] < 2:
            raise ValueError(f"strands: need at least 2 vertices per strand, got {s.shape[2]}")
        if root_uv is not None:
            check_tensor("root_uv", root_uv, shape=(s.shape[1], 2))
            idx = self.nearest_strands(root_uv).to(s.device)
            s = s[:, idx]
        elif s.shape[1] != self.num_roots:
            raise ValueError(
                f"strands: expected {self.num_roots} grid strands without root_uv, got {s.shape[1]}; "
                "pass root_uv to map them onto the grid"
            )
        if s.shape[2] != self.num_vertices:
            from hairwarp.scene.hairstyles import resample_strands

            flat = s.reshape(-1, s.shape[2], 3)
            s = resample_strands(flat, self.num_vertices, dtype=s.dtype).reshape(
                s.shape[0], s.shape[1], self.num_vertices, 3)
        t = self._tensors(s.device, s.dtype)
        b, m = s.shape[:2]
        offsets = (s - s[:, :, :1]).reshape(b, m, -1)
        coeff = offsets @ t["V"] - t["mean"]  # (B, M, K)
        block = (t["U"].T @ coeff).reshape(b, -1)  # (B, A_max * K)
        core = block[:, t["index"]]
        z = (core @ t["P"]) / t["sigma"]
        return z[0] if single else z

    def nearest_strands(self, root_uv: torch.Tensor) -> torch.Tensor:
        """For each grid root, the index of the strand whose root UV is nearest: (M,) int64."""
        uv = root_uv.detach().cpu().double().numpy()
        grid = self.root_uv.astype(np.float64)
        d2 = ((grid[:, None, :] - uv[None, :, :]) ** 2).sum(-1)
        return torch.as_tensor(d2.argmin(axis=1), dtype=torch.int64)

    def sample(self, num: int, generator: torch.Generator | None = None, scale: float = 1.0,
               dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """Random latents z ~ N(0, scale^2 I): (num, L)."""
        return scale * torch.randn(int(num), self.latent_dim, generator=generator, dtype=dtype)

    def _scalp_roots(self, scalp: Scalp, device, dtype) -> torch.Tensor:
        check_tensor("scalp.uv", scalp.uv, shape=(None, 2), allow_empty=False)
        check_tensor("scalp.positions", scalp.positions, shape=(scalp.uv.shape[0], 3))
        uv = scalp.uv.detach().cpu().double().numpy()
        d2 = (self.root_uv[:, None, :].astype(np.float64) - uv[None]) ** 2
        j = torch.as_tensor(d2.sum(-1).argmin(axis=1))
        return scalp.positions.detach()[j.to(scalp.positions.device)].to(device=device, dtype=dtype)


_DEFAULT: HairLatentBasis | None = None


def fit_hair_latent_basis(
    styles: Iterable[np.ndarray],
    scalp: Scalp,
    latent_dim: int = LATENT_DIM,
    strand_dim: int = DEFAULT_STRAND_DIM,
    spatial_modes: tuple[int, ...] | None = DEFAULT_SPATIAL_MODES,
    strand_fit_styles: int = 200,
    info: dict | None = None,
) -> HairLatentBasis:
    """Fit the three-stage linear basis of the module docstring on a corpus.

    Args:
        styles: iterable of (M, N, 3) strand arrays on the scalp grid, in grid order (strand
            i rooted at scalp root i); consumed once. Needs more than `latent_dim` styles.
        scalp: the scalp of the corpus (roots, uv, normals), M roots.
        latent_dim: L (512 in the paper).
        strand_dim: K principal strand shapes.
        spatial_modes: A_k per strand channel (length K), or None for min(M, 320) for all.
        strand_fit_styles: styles kept in memory to fit the strand basis; the rest are
            projected as they come.
        info: extra facts to store.

    Returns:
        The fitted `HairLatentBasis` (its `info` holds the corpus size and the fraction of the
        variance each stage keeps).
    """
    roots = scalp.positions.detach().cpu().double().numpy()
    m = roots.shape[0]
    if spatial_modes is None:
        spatial_modes = (min(m, 320),) * strand_dim
    modes = np.minimum(np.asarray(spatial_modes, dtype=np.int64), m)
    if len(modes) != strand_dim:
        raise ValueError(f"spatial_modes: expected {strand_dim} entries, got {len(modes)}")
    head: list[np.ndarray] = []
    coeffs: list[np.ndarray] = []
    v = None
    n_vertices = None
    for style in styles:
        x = np.asarray(style, dtype=np.float64)
        if x.shape[0] != m or x.ndim != 3 or x.shape[2] != 3:
            raise ValueError(f"styles: expected ({m}, N, 3) arrays, got {x.shape}")
        n_vertices = x.shape[1]
        off = (x - x[:, :1]).reshape(m, -1)
        if v is None:
            head.append(off.astype(np.float32))
            if len(head) == strand_fit_styles:
                v = _strand_basis(head, strand_dim)
                coeffs.extend(h.astype(np.float64) @ v for h in head)
                head = []
        else:
            coeffs.append(off @ v)
    if v is None:
        v = _strand_basis(head, strand_dim)
        coeffs.extend(h.astype(np.float64) @ v for h in head)
    n = len(coeffs)
    if n <= latent_dim:
        raise ValueError(f"styles: need more than latent_dim = {latent_dim} styles, got {n}")
    c = np.stack(coeffs)  # (n, M, K)
    mean = c.mean(axis=0)
    c -= mean
    a = c.transpose(1, 0, 2).reshape(m, -1)
    w, u = np.linalg.eigh(a @ a.T)
    u = np.ascontiguousarray(u[:, ::-1][:, : modes.max()])
    block = np.einsum("ma,nmk->nak", u, c)  # (n, A_max, K)
    core = np.concatenate([block[:, : modes[k], k] for k in range(strand_dim)], axis=1)
    _, s, pt = np.linalg.svd(core, full_matrices=False)
    p = pt[:latent_dim].T
    sigma = s[:latent_dim] / np.sqrt(n)
    total = float((c**2).sum())
    stats = dict(info or {})
    stats.update(
        corpus_styles=n,
        strand_dim=strand_dim,
        spatial_modes=[int(x) for x in modes],
        core_dim=int(core.shape[1]),
        variance_kept_spatial=float((core**2).sum() / total) if total > 0 else 1.0,
        variance_kept_latent=float((s[:latent_dim] ** 2).sum() / (s**2).sum()) if s.sum() > 0 else 1.0,
    )
    return HairLatentBasis(
        strand_basis=v,
        spatial_basis=u,
        spatial_modes=modes,
        mean_coefficients=mean,
        components=p,
        sigma=np.maximum(sigma, 1e-12),
        roots=roots.astype(np.float32),
        root_uv=scalp.uv.detach().cpu().numpy().astype(np.float32),
        root_normals=scalp.normals.detach().cpu().numpy().astype(np.float32),
        num_vertices=int(n_vertices),
        info=stats,
    )


def _strand_basis(offsets: list[np.ndarray], k: int) -> np.ndarray:
    """Top-k principal strand shapes of the uncentred offsets: (N*3, k) orthonormal."""
    gram = np.zeros((offsets[0].shape[1],) * 2)
    for o in offsets:
        o = o.astype(np.float64)
        gram += o.T @ o
    _, vec = np.linalg.eigh(gram)
    return vec[:, ::-1][:, :k].copy()
