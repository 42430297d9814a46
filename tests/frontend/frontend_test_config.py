"""An even smaller model than `tiny`, for fast forward/backward tests."""

import pytest
import torch

from worker.frontend.configs import FrontendConfig

TEST_CONFIG = FrontendConfig(
    name="unit-test", enc_dim=64, enc_depth=2, enc_heads=2, dec_dim=64, dec_depth=4, dec_heads=2,
    state_dec_heads=4, state_size=24, memory_size=8, memory_heads=2, memory_depth=1, ray_enc_depth=1,
    final_transform_depth=1, dpt_layer_dims=(8, 16, 16, 32), dpt_feature_dim=16, dpt_last_dim=8,
    gs_adapter_hidden=32, image_long_side=96,
)


@pytest.fixture(autouse=True, scope="module")
def single_torch_thread():
    """One intra-op thread: on the shared 2-core machine, 2 OpenMP threads under load slow small models 10x+."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
