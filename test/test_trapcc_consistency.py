"""TraPCC's optional temporal-consistency term: one car seen in two neighbouring frames should be
completed alike in its box frame (``consistency``; the pairs are ``metrics.balance.track_partners``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_trapcc import _FixedOutput, _recipe, train_cache  # noqa: F401  (train_cache: a fixture)

from pcc_ros.errors import ConfigError
from pcc_ros.models.recipe import plane_placement, reflect_points
from pcc_ros.models.trapcc_recipe import invert_affine, track_pair_chamfer, training_recipe


def test_pair_chamfer_is_zero_for_one_shape_and_grows_with_the_change():
    rng = np.random.default_rng(0)
    car = torch.from_numpy((rng.uniform(-0.5, 0.5, (2, 300, 3)) * [1, 0.4, 0.35]).astype(np.float32))
    same = torch.cat([car, car[:, torch.randperm(300)]])  # rows i and 2 + i: one car, points in any order
    paired = torch.ones(2, dtype=torch.bool)
    assert float(track_pair_chamfer(same, paired)) < 1e-4
    small, large = (torch.cat([car, car + torch.tensor([0.0, d, 0.0])]) for d in (0.02, 0.1))
    assert 0.005 < float(track_pair_chamfer(small, paired)) < float(track_pair_chamfer(large, paired))
    # a row without a partner (paired False) takes no part
    one = torch.cat([car, torch.stack([car[0], car[1] + 0.3])])
    assert float(track_pair_chamfer(one, torch.tensor([True, False]))) < 1e-4


def test_pair_chamfer_compares_in_the_cars_box_frame():
    """Two crops of one car by detector boxes placed differently: the same car lies shifted and turned in
    the two crops' frames; mapped to the car's labelled box frame (``to_car``) it is the same shape."""
    rng = np.random.default_rng(1)
    car = (rng.uniform(-0.5, 0.5, (1, 300, 3)) * [1, 0.4, 0.35]).astype(np.float32)
    places = np.stack([plane_placement(np.array([0.0, 0.0, 0.0]), np.ones(3)),
                       plane_placement(np.array([0.05, -0.1, np.pi]), np.ones(3))]).astype(np.float32)
    np.testing.assert_allclose(reflect_points(reflect_points(car[0], places[1]), invert_affine(places[1])), car[0],
                               atol=1e-5)
    crops = torch.from_numpy(np.concatenate([reflect_points(car, places[:1]), reflect_points(car, places[1:])]))
    paired = torch.ones(1, dtype=torch.bool)
    assert float(track_pair_chamfer(crops, paired)) > 0.05  # in the crops' own frames they differ
    assert float(track_pair_chamfer(crops, paired, torch.from_numpy(invert_affine(places)))) < 1e-4


def test_partners_are_the_same_track_in_a_neighbouring_frame(train_cache, tmp_path):  # noqa: F811
    recipe = _recipe(tmp_path, consistency=1.0)
    data = recipe.training_data(train_cache, "train", min_points=10)
    keys = train_cache.track_keys()[train_cache.indices("train", min_points=10)]
    frames = train_cache.meta["frame"][train_cache.indices("train", min_points=10)]
    assert (data.partner != np.arange(len(data))).all()  # every car here is seen in 12 frames
    assert (keys[data.partner] == keys).all()
    assert (np.abs(frames[data.partner] - frames) == 1).all()
    assert recipe.data_summary()["sources"][0]["paired"] == len(data)
    batch = next(recipe.batches(data, 6, recipe.build_completer("cpu").config, np.random.default_rng(0)))
    assert batch.batch_size == 6 and batch.paired.tolist() == [True] * 3
    # off by default: plain batches, no pairs, no term
    plain = _recipe(tmp_path)
    batch = next(plain.batches(data, 6, plain.build_completer("cpu").config, np.random.default_rng(0)))
    assert batch.paired is None
    with pytest.raises(ConfigError, match="consistency"):
        training_recipe(consistency=-1.0)


def test_the_term_enters_the_loss_only_when_asked(train_cache, tmp_path):  # noqa: F811
    torch.manual_seed(0)
    recipe = _recipe(tmp_path, consistency=2.0)
    data = recipe.training_data(train_cache, "train", min_points=10)
    completer = recipe.build_completer("cpu")
    batch = next(recipe.batches(data, 4, completer.config, np.random.default_rng(0)))
    _, stats = recipe.loss(completer.model, batch)
    _, base = _recipe(tmp_path).loss(completer.model, batch)
    assert "consistency" not in base and stats["consistency"] > 0  # two frames' inputs differ
    assert stats["loss"] == pytest.approx(base["loss"] + 2.0 * stats["consistency"], rel=1e-5)
    # identical completions of the two frames: the term is zero
    rng = np.random.default_rng(2)
    one = torch.from_numpy(rng.uniform(-0.5, 0.5, (2, 512, 3)).astype(np.float32))
    fixed = _FixedOutput(torch.cat([one, one]), torch.zeros(4, 2, 32, 3))
    batch.to_car = None
    assert recipe.loss(fixed, batch)[1]["consistency"] < 1e-4
