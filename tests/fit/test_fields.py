"""Tests of pd_tool.fit.fields: triplane sampling against a float64 loop reference,
gradients against finite differences, bounds and initial values of the fields."""
from __future__ import annotations

import json
import math

import pytest
import torch

from pd_tool.core.errors import PdToolError
from pd_tool.fit.fields import (
    FieldSettingsError,
    MaterialField,
    Triplane,
    TriplaneField,
    VelocityField,
    tv_loss,
)

TOL64 = 1e-12  # float64 bilinear interpolation: only rounding differs from the loop
TOL32 = 1e-6  # float32 on features of order 0.1-1


def _torch_device(device: str) -> str:
    return "cuda" if device == "cuda" else "cpu"


def bilinear_ref(plane: torch.Tensor, a: float, b: float) -> torch.Tensor:
    """Plain bilinear lookup of plane [C, R, R] at (a, b) in [0,1]^2: a -> column, b -> row.

    Texel j sits at coordinate j / (R - 1) (align_corners=True); outside [0, 1] the
    coordinate is clamped (border padding).
    """
    r = plane.shape[-1]
    u = min(max(a, 0.0), 1.0) * (r - 1)
    v = min(max(b, 0.0), 1.0) * (r - 1)
    j0, i0 = min(int(math.floor(u)), r - 2), min(int(math.floor(v)), r - 2)
    fu, fv = u - j0, v - i0
    out = torch.zeros(plane.shape[0], dtype=torch.float64)
    for c in range(plane.shape[0]):
        out[c] = ((1 - fu) * (1 - fv) * plane[c, i0, j0] + fu * (1 - fv) * plane[c, i0, j0 + 1]
                  + (1 - fu) * fv * plane[c, i0 + 1, j0] + fu * fv * plane[c, i0 + 1, j0 + 1])
    return out


def triplane_ref(planes: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """[N, 3, C] features: plane xy at (x, y), xz at (x, z), yz at (y, z)."""
    out = torch.zeros(x.shape[0], 3, planes.shape[1], dtype=torch.float64)
    for n in range(x.shape[0]):
        px, py, pz = (float(t) for t in x[n])
        for k, (a, b) in enumerate(((px, py), (px, pz), (py, pz))):
            out[n, k] = bilinear_ref(planes[k].double(), a, b)
    return out


def test_triplane_matches_loop_reference_float64():
    torch.manual_seed(0)
    tp = Triplane(5, 3).double()
    # inside the cube, on its faces and slightly outside (border padding)
    x = torch.cat([torch.rand(40, 3, dtype=torch.float64),
                   torch.tensor([[0.0, 1.0, 0.5], [1.0, 0.0, 0.25], [-0.2, 1.3, 0.5]], dtype=torch.float64)])
    got = tp.sample_planes(x)
    ref = triplane_ref(tp.planes.detach(), x)
    assert torch.allclose(got, ref, atol=TOL64, rtol=0)
    # concat keeps plane order xy, xz, yz; sum adds them
    assert torch.allclose(tp(x), ref.reshape(len(x), -1), atol=TOL64, rtol=0)
    tp.reduce = "sum"
    assert torch.allclose(tp(x), ref.sum(dim=1), atol=TOL64, rtol=0)


def test_triplane_texel_centres_hit_texels_exactly():
    # align_corners=True: coordinate j/(R-1) is texel j. Checks axis order too:
    # plane xy is indexed [row = y, column = x].
    r = 4
    tp = Triplane(r, 1)
    with torch.no_grad():
        tp.planes.copy_(torch.arange(3 * r * r, dtype=torch.float32).reshape(3, 1, r, r))
    x = torch.tensor([[1 / 3, 2 / 3, 1.0]])  # column 1 (x), row 2 (y), z -> index 3
    f = tp.sample_planes(x)[0, :, 0]
    p = tp.planes.detach()
    expect = torch.stack([p[0, 0, 2, 1], p[1, 0, 3, 1], p[2, 0, 3, 2]])
    assert torch.allclose(f, expect, atol=1e-5)


def test_triplane_gradcheck_planes_and_positions():
    torch.manual_seed(1)
    tp = Triplane(4, 2).double()
    # points away from texel lines: the bilinear map has kinks there
    x = (0.05 + 0.9 * torch.rand(6, 3, dtype=torch.float64)).requires_grad_(True)
    planes = tp.planes.detach().clone().requires_grad_(True)

    def f(p, xx):  # the module's own code path, with the planes as an input
        return torch.func.functional_call(tp, {"planes": p}, (xx,))

    assert torch.autograd.gradcheck(f, (planes, x), eps=1e-6, atol=1e-7)


def test_tv_loss_matches_definition_and_gradcheck():
    torch.manual_seed(2)
    u = torch.randn(2, 5, 5, dtype=torch.float64)
    ref = 0.0
    for c in range(2):
        for i in range(5):
            for j in range(5):
                if i + 1 < 5:
                    ref += float((u[c, i + 1, j] - u[c, i, j]) ** 2)
                if j + 1 < 5:
                    ref += float((u[c, i, j + 1] - u[c, i, j]) ** 2)
    assert abs(float(tv_loss(u)) - ref) < 1e-10
    assert float(tv_loss(torch.full((3, 4, 4), 2.5))) == 0.0
    assert torch.autograd.gradcheck(tv_loss, (u.clone().requires_grad_(True),))


def test_field_tv_sums_all_three_planes():
    f = MaterialField(8)
    planes = f.net.triplane.planes.detach()
    assert torch.allclose(f.tv(), sum(tv_loss(planes[k]) for k in range(3)))
    f.tv().backward()
    assert f.net.triplane.planes.grad.abs().sum() > 0


def test_material_field_starts_at_init_everywhere(device):
    dev = _torch_device(device)
    torch.manual_seed(3)
    lo, hi, init = math.log(1e3), math.log(1e9), math.log(2e5)
    f = MaterialField(8, lo, hi, init).to(dev)
    x = torch.rand(500, 3, device=dev)
    out = f(x)
    assert out.shape == (500,)
    assert torch.allclose(out, torch.full_like(out, init), atol=1e-4)
    assert torch.allclose(f.youngs_modulus(x[:3]).cpu(), torch.full((3,), 2e5), rtol=1e-4)


def test_material_field_stays_inside_bounds_with_gradient():
    torch.manual_seed(4)
    lo, hi = math.log(1e4), math.log(1e7)
    f = MaterialField(8, lo, hi, math.log(1e5))
    x = torch.rand(100, 3)
    for bias in (-60.0, -5.0, 0.0, 5.0, 60.0):  # pre-activations far to both sides
        with torch.no_grad():
            f.net.last_layer.weight.normal_(0.0, 8.0)
            f.net.last_layer.bias.fill_(bias)
        out = f(x)
        assert torch.isfinite(out).all() and out.min() >= lo and out.max() <= hi
    # near (not at) a bound the gradient is small but alive: no clamp
    with torch.no_grad():
        f.net.last_layer.weight.zero_()
        f.net.last_layer.bias.fill_(8.0)
    out = f(x)
    assert float(out.detach().max()) < hi
    out.sum().backward()
    g = f.net.last_layer.bias.grad
    assert g is not None and float(g) > 0


def test_material_field_learns_a_two_region_target():
    # the gradient path (zero last layer -> hidden layers -> planes) works end to end
    torch.manual_seed(5)
    lo, hi = math.log(1e3), math.log(1e8)
    f = MaterialField(8, lo, hi, math.log(1e5))
    x = torch.rand(400, 3)
    target = torch.where(x[:, 0] < 0.5, math.log(1e4), math.log(1e6))
    opt = torch.optim.Adam(f.parameters(), lr=1e-2)
    first = None
    for _ in range(150):
        opt.zero_grad()
        loss = (f(x) - target).square().mean()
        first = float(loss.detach()) if first is None else first
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.05 * first
    assert f.net.triplane.planes.grad.abs().sum() > 0
    soft, stiff = f(torch.tensor([[0.2, 0.5, 0.5]])), f(torch.tensor([[0.8, 0.5, 0.5]]))
    assert float((stiff - soft).detach()) > math.log(10)


def test_velocity_field_starts_at_rest_and_scales(device):
    dev = _torch_device(device)
    torch.manual_seed(6)
    v = VelocityField(24, scale=0.5).to(dev)
    x = torch.rand(50, 3, device=dev)
    out = v(x)
    assert out.shape == (50, 3)
    assert float(out.detach().abs().max()) == 0.0
    with torch.no_grad():
        v.net.last_layer.bias.copy_(torch.tensor([1.0, -2.0, 0.0]))
    assert torch.allclose(v(x[:1]).cpu(), torch.tensor([[0.5, -1.0, 0.0]]))
    # gradient reaches the last layer at start, and the loss can move v0
    loss = (v(x) - torch.tensor([0.1, 0.0, 0.0], device=dev)).square().sum()
    loss.backward()
    assert v.net.last_layer.weight.grad.abs().sum() > 0


@pytest.mark.parametrize("kind", ["material", "velocity"])
def test_config_and_state_dict_round_trip(kind):
    torch.manual_seed(7)
    f = MaterialField(8, 5.0, 20.0, 11.0, channels=4, hidden=16) if kind == "material" \
        else VelocityField(12, 0.3, channels=4, hidden=16, reduce="sum")
    with torch.no_grad():
        for p in f.parameters():
            p.add_(0.1 * torch.randn_like(p))
    cfg = json.loads(json.dumps(f.config()))  # must survive JSON
    g = (MaterialField if kind == "material" else VelocityField).from_config(cfg)
    g.load_state_dict(f.state_dict())
    x = torch.rand(30, 3)
    assert torch.equal(f(x), g(x))


def test_triplane_field_shapes():
    f = TriplaneField(6, 4, 32, 5)
    assert f(torch.rand(7, 3)).shape == (7, 5)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        f(torch.rand(7, 2))


def test_bad_settings_raise_one_line_errors():
    with pytest.raises(FieldSettingsError, match="not strictly inside"):
        MaterialField(8, math.log(1e3), math.log(1e6), math.log(1e7))
    with pytest.raises(FieldSettingsError, match="bounds are empty"):
        MaterialField(8, 10.0, 5.0, 7.0)
    with pytest.raises(FieldSettingsError, match="resolution"):
        Triplane(1, 4)
    with pytest.raises(FieldSettingsError, match="scale"):
        VelocityField(24, scale=0.0)
    assert issubclass(FieldSettingsError, PdToolError)


def test_field_arrays_round_trip_through_material_file(tmp_path):
    # the lead's .pdmat stores `field.<name>.<param>` float32 arrays + JSON meta
    import numpy as np

    from pd_tool.core.errors import MaterialFileError
    from pd_tool.fit.fields import field_arrays, load_field
    from pd_tool.materials.file import MaterialFile

    torch.manual_seed(8)
    e = MaterialField(8, 5.0, 20.0, 11.0, channels=4, hidden=16)
    v = VelocityField(12, 0.3, channels=4, hidden=16)
    for f in (e, v):
        with torch.no_grad():
            for p in f.parameters():
                p.add_(0.1 * torch.randn_like(p))
    q = 4
    mf = MaterialFile(driver_E=np.full(q, 1e5), driver_v0=np.zeros((q, 3)), driver_rest=np.zeros((q, 3)),
                      meta={"fields": {"material": e.config(), "velocity0": v.config()}},
                      fields={"material": field_arrays(e), "velocity0": field_arrays(v)})
    back = MaterialFile.load(mf.save(tmp_path / "m.pdmat"))
    x = torch.rand(20, 3)
    e2 = load_field(back.meta["fields"]["material"], back.fields["material"])
    v2 = load_field(back.meta["fields"]["velocity0"], back.fields["velocity0"])
    assert torch.equal(e(x), e2(x)) and torch.equal(v(x), v2(x))
    bad = dict(back.fields["material"])
    bad.pop("net.triplane.planes")
    with pytest.raises(MaterialFileError, match="material field weights do not match"):
        load_field(back.meta["fields"]["material"], bad)
    with pytest.raises(MaterialFileError, match="unknown field kind"):
        load_field({"kind": "colour"}, {})
