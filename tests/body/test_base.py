"""BodyTemplate: saved and loaded."""

from __future__ import annotations

import torch

from avatarperfect_cli.body import BodyTemplate


def test_a_saved_template_loads_back_to_the_bit(tmp_path) -> None:
    generator = torch.Generator().manual_seed(0)
    template = BodyTemplate(
        torch.randn(7, 3, generator=generator), torch.randint(0, 7, (4, 3), generator=generator),
        torch.rand(7, 24, generator=generator).softmax(dim=-1), torch.randn(24, 3, generator=generator),
    )  # fmt: skip
    for uvs in (None, (torch.rand(5, 2, generator=generator), torch.randint(0, 5, (4, 3), generator=generator))):
        if uvs is not None:
            template.uvs, template.face_uvs = uvs
        template.save(tmp_path / "template.npz")
        loaded = BodyTemplate.load(tmp_path / "template.npz")
        for name in ("vertices", "faces", "weights", "rest_joints", "uvs", "face_uvs"):
            value, back = getattr(template, name), getattr(loaded, name)
            assert (value is None and back is None) or (torch.equal(value, back) and value.dtype == back.dtype), name
