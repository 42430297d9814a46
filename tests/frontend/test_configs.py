"""Model configurations and the parameter tally (paper config counted on the meta device)."""

from __future__ import annotations

import pytest
import torch

from worker.frontend import CONFIGS, FeedForwardModel, FrontendConfig, build_model, get_config, parameter_tally


@pytest.fixture(scope="module")
def paper() -> FeedForwardModel:
    return build_model("paper", device="meta")


def test_paper_config_matches_table_7(paper: FeedForwardModel) -> None:
    tally = parameter_tally(paper)
    assert tally["total"] == pytest.approx(795.7e6, rel=0.005)
    assert tally["encoder"] == pytest.approx(303.1e6, rel=0.005)
    assert tally["decoder"] == pytest.approx(380.8e6, rel=0.005)
    assert tally["heads_and_tokens"] == pytest.approx(111.8e6, rel=0.03)
    # CUT3R-512's exact counts for the shared parts (cut3r_spec.md section 5).
    assert tally["encoder"] == 303_098_880
    assert tally["decoder"] == 380_762_112
    assert tally["total"] == 793_307_858 + 129 * 7 + 2_361_600


def test_paper_model_without_the_2dgs_additions_is_cut3r_512(paper: FeedForwardModel) -> None:
    model = paper
    head = model.downstream_head
    extra = sum(p.numel() for p in head.gs_adapter.parameters())
    gs_extra = head.dpt_gs.head[4].weight.numel() + head.dpt_gs.head[4].bias.numel() - (3 * 128 + 3)
    assert parameter_tally(model)["total"] - extra - gs_extra == 793_307_858


def test_tiny_is_small_and_sizes_increase() -> None:
    totals = {name: parameter_tally(build_model(name, device="meta"))["total"] for name in CONFIGS}
    assert totals["tiny"] <= 15_000_000
    assert totals["tiny"] < totals["small"] < totals["base"] < totals["paper"]


def test_tally_groups_cover_every_parameter() -> None:
    model = build_model("tiny", device="meta")
    tally = parameter_tally(model)
    assert tally["total"] == sum(p.numel() for p in model.parameters())
    assert min(tally["encoder"], tally["decoder"], tally["heads_and_tokens"]) > 0


def test_config_round_trips_through_dict() -> None:
    config = get_config("small")
    assert FrontendConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ValueError, match="unknown config fields"):
        FrontendConfig.from_dict({**config.to_dict(), "bogus": 1})


def test_invalid_configs_are_rejected() -> None:
    base = get_config("tiny").to_dict()
    with pytest.raises(ValueError, match="divisible"):
        FrontendConfig.from_dict({**base, "enc_heads": 5})
    with pytest.raises(ValueError, match="4 decoder layers"):
        FrontendConfig.from_dict({**base, "dec_depth": 3})
    with pytest.raises(ValueError, match="unknown frontend config"):
        get_config("giant")


def test_dpt_hooks_are_layers_6_9_12_at_paper_depth() -> None:
    assert get_config("paper").dpt_hooks == (6, 9, 12)


def test_meta_model_allocates_nothing(paper: FeedForwardModel) -> None:
    assert all(p.device == torch.device("meta") for p in paper.parameters())
