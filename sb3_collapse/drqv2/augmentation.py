"""DrQ-v2's random-shift image augmentation, computed as an exact integer crop."""

from __future__ import annotations

import torch as th


def draw_shifts(batch_size: int, pad: int, device: th.device | str | None = None) -> th.Tensor:
    """:return: :func:`random_shift`'s integer offsets ``(batch_size, 2)`` in ``[0, 2 * pad]``, as ``(x, y)``, from
    torch's global generator, on ``device``"""
    return th.randint(0, 2 * pad + 1, (batch_size, 2), device=device)


def random_shift(
    obs: th.Tensor, pad: int = 4, shifts: th.Tensor | None = None, channels_last: bool = False
) -> th.Tensor:
    """
    DrQ-v2's random shift: replicate-pad every image by ``pad`` pixels, crop it back at an integer offset per sample
    and axis (gathered directly, the same as the reference's ``grid_sample``: docs/algorithm.md).

    :param obs: images ``(batch, channels, height, width)``, any dtype
    :param pad: padding in pixels; ``0`` returns ``obs`` unchanged
    :param shifts: :func:`draw_shifts`' offsets; ``None``: drawn now
    :param channels_last: return the images in ``channels_last`` memory format (else contiguous)
    :return: shifted images, same shape, dtype and device as ``obs``
    """
    if pad < 0:
        raise ValueError(f"pad must be >= 0 pixels, got {pad}.")
    if obs.dim() != 4:
        raise ValueError(
            f"random_shift expects images of shape (batch, channels, height, width), got {tuple(obs.shape)}."
        )
    if pad == 0:
        return obs
    n, c, h, w = obs.shape
    if shifts is None:
        shifts = draw_shifts(n, pad, obs.device)
    shifts = shifts.to(device=obs.device, dtype=th.long)
    rows = (th.arange(h, device=obs.device).unsqueeze(0) + shifts[:, 1:2] - pad).clamp_(0, h - 1)
    cols = (th.arange(w, device=obs.device).unsqueeze(0) + shifts[:, 0:1] - pad).clamp_(0, w - 1)
    pixels = obs.permute(0, 2, 3, 1).contiguous().view(n * h * w, c)  # free for channels_last input
    first = th.arange(n, device=obs.device).mul_(h * w)
    index = (first[:, None, None] + rows[:, :, None] * w + cols[:, None, :]).view(-1)
    out = pixels.index_select(0, index).view(n, h, w, c).permute(0, 3, 1, 2)
    return out if channels_last else out.contiguous()
