"""NeRF-style frequency encoding."""

import math

import pytest
import torch

from kneas_method.errors import ConfigError, KneasError
from kneas_method.fields.frequency import FrequencyEncoding, FrequencyEncodingConfig


def test_dims_and_values():
    enc = FrequencyEncodingConfig().setup()
    assert isinstance(enc, FrequencyEncoding) and enc.n_output_dims == 3 + 3 * 2 * 6 == 39
    x = torch.tensor([[0.25, -0.5, 1.0], [0.1, 0.2, 0.3]], dtype=torch.float64)
    y = enc(x)
    assert y.shape == (2, 39) and y.dtype == torch.float64
    torch.testing.assert_close(y[:, :3], x)
    for k in range(6):
        block = y[:, 3 + 6 * k: 3 + 6 * (k + 1)]
        torch.testing.assert_close(block[:, :3], torch.sin(2**k * math.pi * x))
        torch.testing.assert_close(block[:, 3:], torch.cos(2**k * math.pi * x))
    # a hand value: sin(2 pi * 0.25) = 1, cos(4 pi * 0.25) = -1
    assert y[0, 3 + 6 * 1 + 0].item() == pytest.approx(1.0)
    assert y[0, 3 + 6 * 2 + 3].item() == pytest.approx(-1.0)


def test_options_and_errors():
    enc = FrequencyEncodingConfig(num_frequencies=2, include_input=False).setup()
    assert enc.n_output_dims == 12 and enc(torch.rand(5, 3)).shape == (5, 12)
    assert FrequencyEncodingConfig(num_frequencies=0).setup()(torch.rand(4, 3)).shape == (4, 3)
    with pytest.raises(ConfigError):
        FrequencyEncodingConfig(num_frequencies=-1).setup()
    with pytest.raises(ConfigError):
        FrequencyEncodingConfig(num_frequencies=0, include_input=False).setup()
    with pytest.raises(KneasError):
        FrequencyEncodingConfig().setup()(torch.rand(4, 2))


def test_differentiable():
    enc = FrequencyEncodingConfig(num_frequencies=3).setup()
    x = (torch.rand(6, 3, dtype=torch.float64) * 2 - 1).requires_grad_(True)
    assert torch.autograd.gradcheck(enc, (x,))
