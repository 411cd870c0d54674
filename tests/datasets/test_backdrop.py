"""The video's backdrop: recovered where frames saw it, unknown where the subject always covers it or it
changes."""

from __future__ import annotations

import torch

from avatarperfect_cli.datasets.backdrop import BackdropConfig, estimate_backdrop


def _video(frames: int = 12, size: int = 40) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A random static room (uint8) and a 10-px square subject sliding right by 2 px per frame."""
    generator = torch.Generator().manual_seed(1)
    room = torch.randint(0, 256, (size, size, 3), generator=generator, dtype=torch.uint8)
    masks = torch.zeros(frames, size, size, dtype=torch.bool)
    for t in range(frames):
        masks[t, 15:25, 5 + 2 * t : 15 + 2 * t] = True
    filmed = torch.where(masks[..., None], torch.tensor([255, 0, 0], dtype=torch.uint8), room)
    return room, masks, filmed


def test_the_room_is_recovered_where_frames_saw_it_and_unknown_where_never_seen() -> None:
    room, masks, filmed = _video()
    config = BackdropConfig(margin=2, min_frames=6, min_share=0.0, reach=0)
    backdrop = estimate_backdrop(filmed, masks, config)
    known = ~backdrop.isnan().any(dim=-1)
    torch.testing.assert_close(backdrop[known], room[known].float() / 255)
    assert known[0].all() and known[:, 0].all()  # far from the subject: seen in every frame
    # (row 20, column 20) lies within 2 px of the square in 7 of the 12 frames: 5 saw it, fewer than 6
    grown = torch.nn.functional.max_pool2d(masks[:, None].float(), 5, stride=1, padding=2)[:, 0] > 0
    seen = (~grown).sum(dim=0)
    assert int(seen[20, 20]) == 5 and not known[20, 20]
    torch.testing.assert_close(known, seen >= 6)


def test_a_pixel_that_changes_between_frames_is_unknown() -> None:
    room, masks, filmed = _video()
    filmed[::2, 2, 3] = 0
    filmed[1::2, 2, 3] = 255
    backdrop = estimate_backdrop(filmed, masks, BackdropConfig(margin=2, min_share=0.0, reach=0))
    assert backdrop[2, 3].isnan().all()
    assert not backdrop[2, 4].isnan().any()


def test_a_plain_wall_goes_on_behind_the_subject_within_reach() -> None:
    # a wall of one colour, a subject that never moves: its pixels are filled with the wall's colour up to
    # `reach` pixels from the nearest seen pixel, and unknown beyond
    masks = torch.zeros(6, 40, 40, dtype=torch.bool)
    masks[:, 5:35, 10:30] = True
    filmed = torch.where(masks[..., None], torch.tensor([255, 0, 0], dtype=torch.uint8), torch.tensor([40, 120, 200], dtype=torch.uint8))
    backdrop = estimate_backdrop(filmed, masks, BackdropConfig(margin=2, min_share=0.0, reach=4))
    seen_edge, inside = 30 + 2, 30 + 2 - 4  # the grown mask's last column, and `reach` columns inside it
    torch.testing.assert_close(backdrop[20, inside], torch.tensor([40, 120, 200]) / 255, atol=1 / 255, rtol=0)
    assert backdrop[20, inside - 2].isnan().all()  # farther from any seen pixel than `reach`
    assert not backdrop[20, seen_edge].isnan().any()
