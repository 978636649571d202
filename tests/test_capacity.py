"""Capacity matching: the width that gives NOSTRA's parameter count is found, and the report says it."""

from dataclasses import asdict

import pytest

from conftest import small_net
from nostra.configs import model_config
from nostra.modality import Modality
from nostra.workflows.capacity import count, markdown, match, table

MODS = [Modality("pos", "lowdim", (3,)), Modality("grip", "lowdim", (2,))]


@pytest.fixture(scope="module")
def configs():
    return {p: model_config(p, net=small_net(p)) for p in ("nostra", "rssm", "lstm")}


def test_the_matched_width_is_the_closest_count_to_nostra(configs):
    target = count("nostra", asdict(configs["nostra"].net), MODS)
    width, n = match(configs["lstm"], target, MODS, "rnn_hidden")
    at = lambda w: count("lstm", {**asdict(configs["lstm"].net), "rnn_hidden": w}, MODS)  # noqa: E731
    assert n == at(width) and abs(n - target) <= min(abs(at(width - 1) - target), abs(at(width + 1) - target))
    assert abs(n - target) / target < 0.02


def test_the_table_matches_lstm_and_rssm_and_says_so(configs):
    rows = {r["policy"]: r for r in table(configs, MODS)}
    assert rows["nostra"]["vs_nostra"] == 1.0 and "knob" not in rows["nostra"]
    for policy, knob in (("lstm", "rnn_hidden"), ("rssm", "latent_dim")):
        r = rows[policy]
        assert r["knob"] == knob and abs(r["matched_params"] / rows["nostra"]["params"] - 1) < 0.05
    text = markdown(list(rows.values()), "cmd")
    assert f"`model.net.rnn_hidden={rows['lstm']['matched']}`" in text and "| BC-RSSM |" in text


def test_a_target_out_of_reach_fails_naming_the_knob(configs):
    with pytest.raises(ValueError, match=r"lstm: net.rnn_hidden=4 gives \d+ parameters, fewer than"):
        match(configs["lstm"], 10**9, MODS, "rnn_hidden", hi=4)


def test_override_prints_the_train_override_that_the_table_lists(capsys):
    """`--override lstm` (what CAPACITY=matched make cpu trains with) is the table's matched width."""
    from nostra.workflows.capacity import configs_for, main

    main(["--profile", "ci", "--task", "lift", "--override", "lstm"])
    printed = capsys.readouterr().out.strip()
    configs, modalities = configs_for("ci", "lift", ["nostra", "lstm"])
    row = next(r for r in table(configs, modalities) if r["policy"] == "lstm")
    assert printed == f"model.net.rnn_hidden={row['matched']}"
