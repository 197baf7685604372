"""Policy files: one card type, consistent views, and a clear error for every kind of bad file."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import pytest
import torch

from marl_amod.checkpoints import PolicyCard, load_policy, read_card, save_policy
from marl_amod.errors import DataError
from marl_amod.models import build_actor
from marl_amod.scenario import grid_city

POLICIES = Path(__file__).resolve().parent.parent / "policies"
ROOT = POLICIES.parent


def _card(city, kind: str = "gnn", hidden: int = 8, **kw) -> dict:
    return {"scenario": city.name, "algorithm": "a2c", "mode": "centralised", "actor": kind, "conv": "gcn",
            "hidden": hidden, "n_features": 13, "lookahead": 6, "seed": 0, **kw}


@pytest.fixture
def policy(tmp_path, tiny_city) -> Path:
    torch.manual_seed(0)
    return save_policy(tmp_path / "p.pt", build_actor("gnn", tiny_city, 13, 8), _card(tiny_city))


def test_views_name_the_pt_they_describe_and_a_stale_view_is_refused(tmp_path, tiny_city, policy):
    assert read_card(policy)["hidden"] == 8
    stale = policy.with_suffix(".json").read_text()
    torch.manual_seed(1)  # another run writes the .pt, then is interrupted before its views
    save_policy(tmp_path / "p.pt", build_actor("gnn", tiny_city, 13, 8), _card(tiny_city))
    policy.with_suffix(".json").write_text(stale)
    with pytest.raises(DataError, match=r"p\.json describes another version of p\.pt"):
        read_card(policy)


def _flip_inside_largest_member(path: Path) -> None:
    with zipfile.ZipFile(path) as zf:
        info = max(zf.infolist(), key=lambda i: i.file_size)
    data = bytearray(path.read_bytes())
    start = info.header_offset + 30 + int.from_bytes(data[info.header_offset + 26:info.header_offset + 28], "little") \
        + int.from_bytes(data[info.header_offset + 28:info.header_offset + 30], "little")
    data[start + info.file_size // 2] ^= 0x10
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda p: p.write_bytes(b""), "is empty"),
        (lambda p: p.write_text("this is not a checkpoint\n"), "a text file"),
        (lambda p: p.write_bytes(p.read_bytes()[: p.stat().st_size // 2]), "truncated"),
        (_flip_inside_largest_member, "fails its checksum"),
    ],
    ids=["zero-byte", "text", "truncated", "bit-flip"],
)
def test_damaged_policy_files_are_a_data_error_naming_the_file(tiny_city, policy, damage, message):
    damage(policy)
    with pytest.raises(DataError, match=message) as info:
        load_policy(policy, tiny_city)
    assert str(policy) in str(info.value)


def test_a_card_without_its_actor_key_names_the_key(tmp_path, tiny_city):
    card = _card(tiny_city)
    del card["actor"]
    path = tmp_path / "noactor.pt"
    torch.save({"format": "marl_amod.policy/2", "card": card, "state_dict": build_actor("gnn", tiny_city, 13, 8).state_dict()}, path)
    with pytest.raises(DataError, match=r"noactor\.pt: its card is incomplete \(actor: missing\)"):
        load_policy(path, tiny_city)


def test_weights_that_do_not_fit_the_card_name_hidden_and_lookahead(tmp_path, tiny_city):
    actor = build_actor("gnn", tiny_city, 13, 8)
    path = tmp_path / "h.pt"
    torch.save({"format": "marl_amod.policy/2", "card": _card(tiny_city, hidden=16), "state_dict": actor.state_dict()}, path)
    with pytest.raises(DataError, match=r"h\.pt: weights do not fit its card \(hidden 16, lookahead 6 = 13 features\)"):
        load_policy(path, tiny_city)
    torch.save({"format": "marl_amod.policy/2", "card": _card(tiny_city, lookahead=4, n_features=9), "state_dict": actor.state_dict()}, path)
    with pytest.raises(DataError, match=r"lookahead 4 = 9 features"):
        load_policy(path, tiny_city)


@pytest.mark.parametrize("kind", ["mlp", "cnn"])
@pytest.mark.parametrize("legacy", [False, True], ids=["card", "format-1 card"])
def test_region_bound_actor_on_a_city_of_another_size_says_use_a_gnn(tmp_path, kind, legacy):
    trained, other = grid_city(4, 4, seed=0, horizon=4), grid_city(2, 7, seed=0, horizon=4)
    card = _card(trained, kind) | ({} if legacy else {"n_regions": 16})
    path = save_policy(tmp_path / f"{kind}.pt", build_actor(kind, trained, 13, 8), card)
    with pytest.raises(DataError, match=rf"{kind}\.pt: trained for 16 regions; {other.name} has 14; MLP and CNN actors are tied "
                                        "to a region count — use a GNN policy"):
        load_policy(path, other)


def test_policy_card_is_the_one_type_with_env_version_and_commit(tmp_path, tiny_city):
    from marl_amod.checkpoints import make_card

    card = make_card(**_card(tiny_city), profit_mean=1.0, config="configs/a2c/synthetic.yaml")
    assert card.env_version == "v0" and card.to_dict()["config"] == "configs/a2c/synthetic.yaml"
    assert card.git_commit is None or len(card.git_commit.split("+")[0]) == 40
    assert card.platform["torch"] == torch.__version__ and card.platform["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert card.platform["cpu"]  # what the run's floating point depends on, for a retrain elsewhere that differs
    path = save_policy(tmp_path / "c.pt", build_actor("gnn", tiny_city, 13, 8), card)
    on_disk = json.loads(path.with_suffix(".json").read_text())
    assert PolicyCard.model_validate(on_disk).env_version == "v0"
    assert "marl-amod train --config configs/a2c/synthetic.yaml" in path.with_suffix(".md").read_text()


@pytest.mark.parametrize("pt", sorted(POLICIES.glob("*.pt")), ids=lambda p: p.stem)
def test_shipped_cards_are_consistent_views_of_their_pt_and_name_an_existing_config(pt):
    card = read_card(pt)  # checks the .json's SHA-256 against the .pt
    assert card["env_version"] == "v0"
    assert (ROOT / card["config"]).is_file(), card["config"]
    assert card["config"] in pt.with_suffix(".md").read_text()
    blob = torch.load(pt, map_location="cpu", weights_only=True)
    assert {k: v for k, v in blob["card"].items()} == {k: v for k, v in card.items()}


def test_shipped_synthetic_policies_load_and_match_their_card(small_city):
    from marl_amod.evaluation import evaluate

    pt = POLICIES / "a2c_gnn_synthetic.pt"
    card = read_card(pt)
    result = evaluate(load_policy(pt, small_city), small_city, episodes=card["eval_episodes"], seed=card["eval_seed"])
    assert result["metrics"]["profit"]["mean"] == pytest.approx(card["profit_mean"], rel=1e-12)
