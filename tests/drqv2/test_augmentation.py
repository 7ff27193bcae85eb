import pytest
import torch as th
import torch.nn.functional as F

from sb3_collapse.drqv2.augmentation import random_shift
from tests.drqv2_reference import random_shift_grid_sample


def _images(n=8, c=9, h=84, w=84, seed=0):
    generator = th.Generator().manual_seed(seed)
    return th.randint(0, 256, (n, c, h, w), dtype=th.uint8, generator=generator)


def test_keeps_shape_dtype_device():
    obs = _images()
    out = random_shift(obs, pad=4)
    assert out.shape == obs.shape
    assert out.dtype == th.uint8
    assert out.device == obs.device
    float_out = random_shift(obs.float(), pad=4)
    assert float_out.dtype == th.float32


def test_pad_zero_is_identity():
    obs = _images()
    assert random_shift(obs, pad=0) is obs


@pytest.mark.parametrize("pad", [1, 4])
def test_equals_reference_grid_sample(pad):
    obs = _images(n=16, h=40, w=40)
    shifts = th.randint(0, 2 * pad + 1, (16, 2))
    ours = random_shift(obs, pad=pad, shifts=shifts).float()
    reference = random_shift_grid_sample(obs.float(), pad=pad, shifts=shifts)
    assert th.allclose(ours, reference, atol=0.02)


def test_random_shift_is_a_crop_of_the_padded_image_within_4_pixels():
    th.manual_seed(0)
    obs = _images(n=32, h=30, w=30)
    out = random_shift(obs, pad=4)
    padded = F.pad(obs.float(), (4, 4, 4, 4), mode="replicate")
    offsets = set()
    for i in range(obs.shape[0]):
        matches = [
            (dx, dy)
            for dy in range(9)
            for dx in range(9)
            if th.equal(padded[i, :, dy : dy + 30, dx : dx + 30], out[i].float())
        ]
        assert matches, f"sample {i} is not a shift of at most 4 pixels"
        offsets.add(matches[0])
    # Independent shifts per sample: 32 draws from 81 offsets are not all the same.
    assert len(offsets) > 1


def test_shift_values():
    obs = th.arange(5 * 5, dtype=th.float32).view(1, 1, 5, 5)
    # Offset 4 on both axes is the centre of the padded image: the identity.
    assert th.equal(random_shift(obs, pad=4, shifts=th.tensor([[4, 4]])), obs)
    # Offset (5, 4): one pixel to the right, last column replicated.
    shifted = random_shift(obs, pad=4, shifts=th.tensor([[5, 4]]))
    assert th.equal(shifted[0, 0, :, :4], obs[0, 0, :, 1:])
    assert th.equal(shifted[0, 0, :, 4], obs[0, 0, :, 4])


def test_bad_input():
    with pytest.raises(ValueError, match="pad"):
        random_shift(_images(), pad=-1)
    with pytest.raises(ValueError, match="batch, channels, height, width"):
        random_shift(th.zeros(9, 84, 84), pad=4)


def test_channels_last_output_has_the_same_images():
    obs = _images(n=5, h=20, w=24)
    shifts = th.randint(0, 9, (5, 2))
    contiguous = random_shift(obs, pad=4, shifts=shifts)
    channels_last = random_shift(obs, pad=4, shifts=shifts, channels_last=True)
    assert contiguous.is_contiguous()
    assert channels_last.is_contiguous(memory_format=th.channels_last) and not channels_last.is_contiguous()
    assert th.equal(channels_last, contiguous)
    # A channels_last input gives the same images too.
    assert th.equal(random_shift(obs.contiguous(memory_format=th.channels_last), pad=4, shifts=shifts), contiguous)
