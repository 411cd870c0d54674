"""The Gaussians container: shape checks, derived quantities, SH degree bookkeeping."""

from __future__ import annotations

import pytest
import torch

from avatarperfect_cli.gaussians import Gaussians, num_sh_bases, sh_degree_from_bases


def make(n: int = 4, bases: int = 4, **overrides) -> Gaussians:
    fields = dict(
        means=torch.zeros(n, 3),
        quats=torch.tensor([[2.0, 0, 0, 0]]).repeat(n, 1),
        log_scales=torch.log(torch.full((n, 3), 0.01)),
        opacity_logits=torch.zeros(n),
        sh=torch.zeros(n, bases, 3),
    )
    fields.update(overrides)
    return Gaussians(**fields)


def test_derived_quantities():
    g = make()
    assert len(g) == 4 and g.sh_degree == 1
    torch.testing.assert_close(g.scales, torch.full((4, 3), 0.01))
    torch.testing.assert_close(g.opacities, torch.full((4,), 0.5))
    torch.testing.assert_close(g.unit_quats, torch.tensor([[1.0, 0, 0, 0]]).repeat(4, 1))


@pytest.mark.parametrize(
    "override,message",
    [
        ({"quats": torch.zeros(4, 3)}, "quats"),
        ({"log_scales": torch.zeros(3, 3)}, "log_scales"),
        ({"opacity_logits": torch.zeros(4, 1)}, "opacity_logits"),
        ({"sh": torch.zeros(4, 5, 3)}, "degree"),
        ({"extras": {"skin_weights": torch.zeros(3, 24)}}, "skin_weights"),
    ],
)
def test_inconsistent_shapes_are_rejected(override, message):
    with pytest.raises(ValueError, match=message):
        make(**override)


def test_sh_bases_and_degrees_invert():
    assert [num_sh_bases(d) for d in range(4)] == [1, 4, 9, 16]
    assert [sh_degree_from_bases(b) for b in (1, 4, 9, 16)] == [0, 1, 2, 3]
    with pytest.raises(ValueError):
        num_sh_bases(4)
    with pytest.raises(ValueError):
        sh_degree_from_bases(25)


def test_to_moves_floats_and_keeps_extras():
    g = make(extras={"skin_weights": torch.rand(4, 24)}).to(dtype=torch.float64)
    assert g.means.dtype == torch.float64 and g.extras["skin_weights"].dtype == torch.float64
