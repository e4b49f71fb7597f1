"""The total energy (Eq. 5 / Eq. 6 without L_func_reg): composition, plain-torch agreement,
gradients, and the term switches."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from hairwarp.config import ALL_TERMS, EnergyConfig
from hairwarp.energy import EnergyInputs, dynamic_energy, static_energy, total_energy
from hairwarp.ops import BodyMesh
from hairwarp.torch_reference import energy as ref_energy
from meshes import icosphere

# float64 throughout; the Warp path and plain torch evaluate the same formulas, the body's
# closest point comes from a float32 BVH and is refined in float64 (about 1e-7 of coordinates).
_RTOL = 1e-6


def _scene(device=torch.device("cpu"), dtype=torch.float64, strands=12, vertices=16, batch=2, seed=0):
    """Strands hanging from a unit-radius-0.1 m sphere 'head', some tips pushed inside."""
    rng = np.random.default_rng(seed)
    verts, faces = icosphere(frequency=6, radius=0.1)
    verts = torch.as_tensor(verts, dtype=dtype)
    faces = torch.as_tensor(faces, dtype=torch.int32)
    theta = rng.uniform(0.2, 1.2, strands)
    phi = rng.uniform(0, 2 * np.pi, strands)
    dirs = np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], 1)
    roots = 0.1 * dirs
    s = np.linspace(0, 0.12, vertices)[:, None]
    x = roots[:, None, :] + s[None] * np.array([0.0, -1.0, 0.0]) + 0.01 * s[None] * dirs[:, None, :]
    x = torch.as_tensor(x, dtype=dtype)
    rest = (x[:, 1:] - x[:, :-1]).norm(dim=-1)
    xb = x.expand(batch, -1, -1, -1).clone()
    xb[-1, :, 2:] += torch.as_tensor(rng.normal(0, 2e-3, (strands, vertices - 2, 3)), dtype=dtype)
    normals = torch.as_tensor(dirs, dtype=dtype)
    verts, faces, x, xb, rest, normals = (t.to(device) for t in (verts, faces, x, xb, rest, normals))
    body = BodyMesh(verts, faces)
    inputs = EnergyInputs(rest_lengths=rest, rigid=x.expand(batch, -1, -1, -1).clone(),
                          scalp_normals=normals, body=body)
    return xb, inputs


def _config():
    # hair-hair on with a diameter the test strands reach, so every term is non-zero
    return EnergyConfig(hair_diameter=3e-3, hair_hair_dhat=4.5e-3, hair_hair_weight=1e6,
                        barrier_join_fraction=0.5)


def test_total_is_the_sum_of_its_terms_and_every_term_is_present(device):
    x, inputs = _scene(device)
    cfg = _config()
    prev = x.detach() - 1e-3
    result = dynamic_energy(x, replace(inputs, prev=prev, prev2=prev - 1e-3), cfg)
    assert set(result.terms) == set(ALL_TERMS)
    assert result.hair_hair_pairs > 0
    assert float(result.terms["hair_body_contact"].abs().sum()) > 0
    summed = sum(result.terms.values())
    torch.testing.assert_close(result.total.detach(), summed, rtol=_RTOL, atol=0)


def test_matches_plain_torch_reference_value_and_gradient(device):
    x, inputs = _scene(device)
    cfg = _config()
    xw = x.clone().requires_grad_(True)
    xt = x.clone().requires_grad_(True)
    ew = static_energy(xw, inputs, cfg)
    et = ref_energy.total_energy(xt, inputs, cfg, hair_body="exact")
    assert ew.hair_hair_pairs == et.hair_hair_pairs > 0
    torch.testing.assert_close(ew.total.detach(), et.total.detach(), rtol=_RTOL, atol=1e-12)
    ew.total.sum().backward()
    et.total.sum().backward()
    assert float(xw.grad.abs().max()) > 0
    torch.testing.assert_close(xw.grad, xt.grad, rtol=1e-5, atol=1e-9)
    assert float(xw.grad[:, :, :2].abs().max()) == 0.0  # vertices 0 and 1 are fixed


def test_gradient_matches_finite_differences(device):
    x, inputs = _scene(device, strands=4, vertices=8, batch=1)
    cfg = _config()
    x = x.clone().requires_grad_(True)
    static_energy(x, inputs, cfg).total.sum().backward()
    g = x.grad
    rng = np.random.default_rng(3)
    h = 1e-7
    for _ in range(6):
        s, v, k = rng.integers(0, 4), rng.integers(2, 8), rng.integers(0, 3)
        xp, xm = x.detach().clone(), x.detach().clone()
        xp[0, s, v, k] += h
        xm[0, s, v, k] -= h
        fd = (static_energy(xp, inputs, cfg).total - static_energy(xm, inputs, cfg).total) / (2 * h)
        assert abs(float(fd) - float(g[0, s, v, k])) <= 1e-4 * max(1.0, abs(float(fd)))


def test_term_subset_and_zero_weights_switch_terms_off(device):
    x, inputs = _scene(device)
    cfg = _config()
    only = static_energy(x, inputs, cfg, terms=("stretch", "gravity"))
    assert set(only.terms) == {"stretch", "gravity"}
    no_contact = static_energy(x, inputs, cfg.replace(hair_body_weight=0.0, hair_hair_weight=0.0))
    assert "hair_body_contact" not in no_contact.terms and "hair_hair_contact" not in no_contact.terms
    with pytest.raises(ValueError, match="terms"):
        static_energy(x, inputs, cfg, terms=("stretchh",))


def test_dynamic_energy_needs_previous_states_and_adds_inertia(device):
    x, inputs = _scene(device)
    with pytest.raises(ValueError, match="prev"):
        dynamic_energy(x, inputs, _config())
    moved = replace(inputs, prev=x.detach() + 1e-2, prev2=x.detach() + 2e-2)
    dyn = dynamic_energy(x, moved, _config())
    stat = static_energy(x, inputs, _config())
    assert float(dyn.terms["inertia"].min()) > 0
    torch.testing.assert_close(dyn.total - dyn.terms["inertia"], stat.total, rtol=_RTOL, atol=1e-12)


def test_unbatched_input_gives_one_value(device):
    x, inputs = _scene(device, batch=1)
    r = total_energy(x[0], replace(inputs, rigid=inputs.rigid[0]), _config())
    assert r.total.shape == (1,)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("chunks", [1, 3])
def test_kernel_row_sums_equal_torch_sums(dtype, chunks):
    """The block row sums the energies use on CUDA (`hairwarp.ops.reductions`), run on the CPU:
    each row's sum, whatever the blocks a row is split into (float64 accumulation)."""
    from hairwarp.ops.reductions import kernel_row_sums, row_sums

    gen = torch.Generator().manual_seed(chunks)
    values = torch.randn(7, 1001, generator=gen, dtype=torch.float64).to(dtype)
    expected = values.double().sum(dim=1)
    got = kernel_row_sums(values, chunks)
    assert got.dtype == dtype and got.shape == (7,)
    torch.testing.assert_close(got.double(), expected, rtol=1e-6 if dtype == torch.float32 else 1e-12, atol=1e-5)
    torch.testing.assert_close(row_sums(values).double(), expected, rtol=1e-5, atol=1e-4)
