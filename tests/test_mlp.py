"""AdaptiveMLP (the paper's growing search) and its ONNX surface map."""

import pickle

import numpy as np
import pytest
from failing_pools import BrokenPool, LostWorkers

from reconstruct.errors import InvalidInputError, NotFittedError
from reconstruct.mlp import SPLIT, AdaptiveMLP
from reconstruct.surface_map import OnnxSurfaceMap

SMALL = {"max_layers": 2, "max_neurons": 6, "max_epochs": 15, "final_epochs": 40}


def paraboloid(n=600, sigma=0.0, seed=0):
    """(n, 2) parameters in [-1, 1]² and (n, 3) points on z = x² - y² (scaled, offset)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(-1, 1, size=(n, 2))
    z = 5 * (uv[:, 0] ** 2 - uv[:, 1] ** 2)
    xyz = np.column_stack([10 * uv[:, 0] + 50, 10 * uv[:, 1] - 20, z])
    return uv, xyz + rng.normal(0, sigma, size=xyz.shape)


@pytest.fixture(scope="module")
def fitted():
    uv, xyz = paraboloid()
    return AdaptiveMLP(random_state=0, **SMALL).fit(uv, xyz), uv, xyz


def test_learns_a_smooth_map_to_well_below_its_scale(fitted):
    model, uv, xyz = fitted
    rms = np.sqrt(np.mean((model.predict(uv) - xyz) ** 2))
    assert rms < 0.05  # the targets span ±10 (x, y) and ±5 (z)
    fresh_uv, fresh_xyz = paraboloid(200, seed=1)  # and generalises
    assert np.sqrt(np.mean((model.predict(fresh_uv) - fresh_xyz) ** 2)) < 0.1


def test_onnx_equals_torch_within_1e_5(fitted):
    model, uv, _ = fitted
    grid = np.stack(np.meshgrid(np.linspace(-1.2, 1.2, 70), np.linspace(-1.2, 1.2, 70)), -1)
    for probe in (uv, grid.reshape(-1, 2)):
        np.testing.assert_allclose(model.predict(probe), model.predict_torch(probe), atol=1e-5)


def test_search_follows_the_paper(fitted):
    model, _, _ = fitted
    searched = [h["layers"] for h in model.history_ if "final" not in h and "retry" not in h]
    assert searched[0] == (1,)  # one hidden layer of one neuron first
    widths = [layers[0] for layers in searched if len(layers) == 1]
    assert widths == list(range(1, len(widths) + 1))  # then one neuron at a time
    assert all(len(b) >= len(a) for a, b in zip(searched, searched[1:], strict=False))
    assert all(len(layers) <= SMALL["max_layers"] for layers in searched)
    assert max(max(layers) for layers in searched) <= SMALL["max_neurons"]
    assert model.hidden_layers_ in searched
    assert SPLIT == (0.85, 0.10, 0.05)
    for record in model.history_:
        assert {"train_mse", "test_mse", "validation_mse", "weighted_mse", "epochs"} <= set(record)


def test_more_neurons_fit_better_until_the_search_stops(fitted):
    model, _, _ = fitted
    first_layer = [h for h in model.history_ if len(h["layers"]) == 1 and "final" not in h]
    assert first_layer[-1]["weighted_mse"] < 0.1 * first_layer[0]["weighted_mse"]


def test_same_seed_same_network():
    uv, xyz = paraboloid(300, sigma=0.1)
    a = AdaptiveMLP(random_state=3, **SMALL).fit(uv, xyz)
    b = AdaptiveMLP(random_state=3, **SMALL).fit(uv, xyz)
    assert a.hidden_layers_ == b.hidden_layers_
    np.testing.assert_array_equal(a.predict(uv), b.predict(uv))
    assert a.surface_map_.to_bytes() == b.surface_map_.to_bytes()


def test_search_then_finish_is_fit_and_the_searched_map_comes_first():
    uv, xyz = paraboloid(300, sigma=0.1)
    whole = AdaptiveMLP(random_state=3, **SMALL).fit(uv, xyz)
    apart = AdaptiveMLP(random_state=3, **SMALL).search(uv, xyz)
    assert apart.hidden_layers_ == whole.hidden_layers_
    provisional = apart.predict(uv)  # the searched net, before its final fits
    assert not hasattr(apart, "torch_model_")
    apart.finish()
    np.testing.assert_array_equal(apart.predict(uv), whole.predict(uv))
    assert np.mean((provisional - xyz) ** 2) > np.mean((whole.predict(uv) - xyz) ** 2)
    with pytest.raises(NotFittedError, match="search"):
        apart.finish()  # once only


@pytest.mark.parametrize("activation", ["sigmoid", "relu"])
def test_activation_is_selectable(activation):
    uv, xyz = paraboloid(300)
    model = AdaptiveMLP(activation=activation, random_state=0, **SMALL).fit(uv, xyz)
    names = {type(m).__name__.lower() for m in model.torch_model_}
    assert {"sigmoid": "sigmoid", "relu": "relu"}[activation] in names
    assert type(list(model.torch_model_)[-1]).__name__ == "Linear"  # linear output
    np.testing.assert_allclose(model.predict(uv), model.predict_torch(uv), atol=1e-5)


def test_retrain_on_all_data_is_recorded():
    uv, xyz = paraboloid(300)
    model = AdaptiveMLP(retrain=True, random_state=0, **SMALL).fit(uv, xyz)
    assert model.history_[-1].get("retrained") is True
    assert np.sqrt(np.mean((model.predict(uv) - xyz) ** 2)) < 0.2
    widths = [m.out_features for m in model.torch_model_ if hasattr(m, "out_features")][:-1]
    assert tuple(widths) == model.hidden_layers_  # one retrained net, not a mean


def test_the_chosen_net_is_the_mean_of_its_final_fits_that_agree(fitted):
    from reconstruct.mlp import MEAN_GUARD

    model, _, _ = fitted
    finals = [h for h in model.history_ if "final" in h]
    assert [h["final"] for h in finals] == ["warm"] + ["fresh"] * model.final_starts
    errors = [h["weighted_mse"] for h in finals]
    widths = [m.out_features for m in model.torch_model_ if hasattr(m, "out_features")][:-1]
    factor = sum(e <= MEAN_GUARD * min(errors) for e in errors)
    assert tuple(widths) == tuple(factor * w for w in model.hidden_layers_)


def test_fine_tune_keeps_the_architecture_and_improves_on_new_data(fitted):
    model, _, _ = fitted
    uv, xyz = paraboloid(400, seed=5)
    shifted = xyz + np.array([0.0, 0.0, 0.5])  # the surface moved: a new view refines it
    before = np.sqrt(np.mean((model.predict(uv) - shifted) ** 2))
    layers = model.hidden_layers_
    clone = pickle.loads(pickle.dumps(model))
    clone.fine_tune(uv, shifted)
    assert clone.hidden_layers_ == layers
    assert np.sqrt(np.mean((clone.predict(uv) - shifted) ** 2)) < 0.5 * before


def test_surface_map_round_trips_and_pickles(fitted):
    model, uv, _ = fitted
    again = OnnxSurfaceMap.from_bytes(model.surface_map_.to_bytes())
    np.testing.assert_array_equal(again(uv), model.predict(uv))
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(again))(uv[:5]), again(uv[:5]))
    assert again(np.empty((0, 2))).shape == (0, 3)
    with pytest.raises(InvalidInputError, match=r"takes \(n, 2\)"):
        again(np.zeros((4, 3)))


def test_surface_map_rejects_garbage_bytes():
    with pytest.raises(InvalidInputError, match="not a usable ONNX surface map"):
        OnnxSurfaceMap(b"definitely not onnx")


def test_inference_does_not_need_torch(fitted, tmp_path):
    import subprocess
    import sys

    model, _, _ = fitted
    path = tmp_path / "map.onnx"
    path.write_bytes(model.surface_map_.to_bytes())
    code = (
        "import sys, numpy as np; sys.modules['torch'] = None\n"
        "from reconstruct.surface_map import OnnxSurfaceMap\n"
        f"m = OnnxSurfaceMap(open({str(path)!r}, 'rb').read())\n"
        "print(m(np.zeros((3, 2))).shape)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "(3, 3)"


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"activation": "swish"}, "activation must be one of"),
        ({"max_neurons": 0}, "max_neurons must be a whole number >= 1"),
        ({"test_weight": 2}, r"test_weight must be in \[0, 1\]"),
    ],
)
def test_bad_parameters_are_named(params, message):
    uv, xyz = paraboloid(100)
    with pytest.raises(InvalidInputError, match=message):
        AdaptiveMLP(**params).fit(uv, xyz)


def test_bad_samples_are_named():
    uv, xyz = paraboloid(100)
    with pytest.raises(InvalidInputError, match="at least 20 samples"):
        AdaptiveMLP().fit(uv[:10], xyz[:10])
    bad = xyz.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InvalidInputError, match="NaN"):
        AdaptiveMLP().fit(uv, bad)
    with pytest.raises(InvalidInputError, match=r"\(n, d_in\)"):
        AdaptiveMLP().fit(uv, xyz[:50])
    with pytest.raises(NotFittedError):
        AdaptiveMLP().predict(uv)


@pytest.mark.parametrize("n", [20, 36, 144, 1600])
def test_the_split_is_85_10_5_disjoint_with_two_held_out_samples_at_least(n):
    parts = AdaptiveMLP()._split(n, np.random.default_rng(0))
    train, test, validation = parts["train"], parts["test"], parts["validation"]
    assert len(test) >= 2 and len(validation) >= 2
    assert len(train) + len(test) + len(validation) == n
    assert len(set(train) | set(test) | set(validation)) == n
    if n >= 144:
        assert abs(len(train) / n - 0.85) < 0.01 and abs(len(test) / n - 0.10) < 0.01


@pytest.mark.parametrize(("n", "cap", "n_bags", "covered"),
                         [(1600, 6000, 1, 1360), (500, 300, 3, 425), (1000, 300, 3, 850),
                          (5000, 300, 3, 900)])
def test_the_final_fits_of_a_large_cloud_each_train_on_a_share_of_its_own(n, cap, n_bags,
                                                                         covered):
    parts = AdaptiveMLP(max_train_points=cap)._split(n, np.random.default_rng(0))
    held_out = set(parts["test"]) | set(parts["validation"])
    seen = set()
    assert len(parts["bags"]) == n_bags
    disjoint = n_bags * cap <= covered  # the training part holds every share whole
    for bag in parts["bags"]:
        assert len(bag) == min(cap, covered) and not set(bag) & held_out
        assert not (disjoint and set(bag) & seen)
        seen |= set(bag)
    assert len(seen) == covered
    assert set(parts["train"]) <= seen
    better = AdaptiveMLP(max_train_points=cap, final_fit="better")._split(
        n, np.random.default_rng(0))  # compares its fits' errors: on the same samples
    assert len(better["bags"]) == 1 and np.array_equal(better["bags"][0], better["train"])


def test_each_final_fit_trains_on_its_own_bag(monkeypatch):
    import reconstruct.mlp as mlp_module

    train, rows = mlp_module.AdaptiveMLP._train, []

    def spy(self, net, tensors, max_epochs=None, patience=None, decay=0.0):
        if max_epochs == self.final_epochs:
            rows.append({tuple(r) for r in tensors["train"][0].numpy()})
        return train(self, net, tensors, max_epochs, patience, decay)

    monkeypatch.setattr(mlp_module.AdaptiveMLP, "_train", spy)
    uv, xyz = paraboloid(1000)
    AdaptiveMLP(hidden_layers=(3,), final_epochs=3, max_train_points=250, random_state=0).fit(
        uv, xyz)
    assert len(rows) == 3 and all(len(r) == 250 for r in rows)
    assert not rows[0] & rows[1] and not rows[1] & rows[2] and not rows[0] & rows[2]


def test_final_fits_in_a_worker_process_give_the_same_net_as_here(caplog, monkeypatch):
    from joblib.externals.loky import ProcessPoolExecutor

    uv, xyz = paraboloid(1000)
    params = dict(hidden_layers=(4,), final_epochs=30, max_train_points=250, random_state=0)
    here = AdaptiveMLP(**params).fit(uv, xyz)
    train, trained_here = AdaptiveMLP._train, []

    def counted(self, *args, **kwargs):  # this process only: the worker is not patched
        trained_here.append(1)
        return train(self, *args, **kwargs)

    monkeypatch.setattr(AdaptiveMLP, "_train", counted)
    with ProcessPoolExecutor(max_workers=1) as pool, caplog.at_level("INFO", "reconstruct.mlp"):
        elsewhere = AdaptiveMLP(**params).search(uv, xyz).finish(pool, n_workers=1)
    assert "1 of 3 final fits in worker processes" in caplog.text
    assert len(trained_here) == 2  # the warm start and one fresh start; the other elsewhere
    np.testing.assert_array_equal(here.predict(uv), elsewhere.predict(uv))
    assert [r["epochs"] for r in here.history_] == [r["epochs"] for r in elsewhere.history_]


@pytest.mark.parametrize(("pool", "said"), [
    (BrokenPool(), "workers unavailable (the pool is broken); training here"),
    (LostWorkers(), "worker failed (worker killed); training it here"),
])
def test_final_fits_whose_workers_fail_are_trained_here(pool, said, caplog):
    uv, xyz = paraboloid(1000)
    params = dict(hidden_layers=(4,), final_epochs=30, random_state=0)
    here = AdaptiveMLP(**params).fit(uv, xyz)
    with caplog.at_level("WARNING", "reconstruct.mlp"):
        failed = AdaptiveMLP(**params).search(uv, xyz).finish(pool, n_workers=2)
    assert said in caplog.text
    np.testing.assert_array_equal(here.predict(uv), failed.predict(uv))


@pytest.mark.parametrize("layers", [(4,), (5, 3)])
def test_the_final_net_is_the_mean_of_two_fits_as_one_mlp(layers):
    import torch

    from reconstruct.networks import build as _build
    from reconstruct.networks import mean_of as _mean_of

    generator = torch.Generator().manual_seed(0)
    a, b, c = (_build(layers, "tanh", 2, 3, generator) for _ in range(3))
    x = torch.from_numpy(np.random.default_rng(0).normal(size=(50, 2)))
    for nets in ((a, b), (a, b, c)):
        merged = _mean_of(*nets)
        with torch.no_grad():
            np.testing.assert_allclose(merged(x), sum(n(x) for n in nets) / len(nets),
                                       rtol=1e-12, atol=1e-12)
        widths = [m.out_features for m in merged if isinstance(m, torch.nn.Linear)]
        assert widths == [len(nets) * w for w in layers] + [3]


def test_final_fit_better_keeps_one_net_and_bad_values_are_refused():
    uv, xyz = paraboloid(300)
    model = AdaptiveMLP(final_fit="better", random_state=0, **SMALL).fit(uv, xyz)
    widths = [m.out_features for m in model.torch_model_ if hasattr(m, "out_features")][:-1]
    assert tuple(widths) == model.hidden_layers_
    with pytest.raises(InvalidInputError, match="final_fit"):
        AdaptiveMLP(final_fit="best", **SMALL).fit(uv, xyz)


@pytest.mark.parametrize(("fresh_factor", "mean_kept"), [(1.02, True), (1.5, False)])
def test_the_mean_is_kept_only_while_the_final_fits_agree(monkeypatch, fresh_factor,
                                                          mean_kept):
    """A final fit whose weighted error is over 5 % above the best one's stalled: left out."""
    import reconstruct.mlp as mlp_module

    train = mlp_module.AdaptiveMLP._train

    def train_with_a_worse_fresh_fit(self, net, tensors, max_epochs=None, patience=None,
                                     decay=0.0):
        record = train(self, net, tensors, max_epochs, patience, decay)
        if max_epochs == self.final_epochs:
            self._finals = getattr(self, "_finals", 0) + 1
            if self._finals == 1:
                self._warm_mse = record["weighted_mse"]
            else:
                record["weighted_mse"] = fresh_factor * self._warm_mse
        return record

    monkeypatch.setattr(mlp_module.AdaptiveMLP, "_train", train_with_a_worse_fresh_fit)
    uv, xyz = paraboloid(300)
    model = AdaptiveMLP(random_state=0, **SMALL).fit(uv, xyz)
    widths = [m.out_features for m in model.torch_model_ if hasattr(m, "out_features")][:-1]
    factor = 1 + model.final_starts if mean_kept else 1
    assert tuple(widths) == tuple(factor * w for w in model.hidden_layers_)


def scripted_search(monkeypatch, scores):
    """Make the search's weighted errors ``scores[layers]`` (a list: one per start)."""
    import reconstruct.mlp as mlp_module

    train = mlp_module.AdaptiveMLP._train
    starts = {}

    def train_scripted(self, net, tensors, max_epochs=None, patience=None, decay=0.0):
        record = train(self, net, tensors, 2 if max_epochs is None else max_epochs, patience,
                       decay)
        if max_epochs is None:  # a searched configuration
            layers = tuple(m.out_features for m in net if hasattr(m, "out_features"))[:-1]
            run = starts[layers] = starts.get(layers, -1) + 1
            record["weighted_mse"] = scores[layers][min(run, len(scores[layers]) - 1)]
        return record

    monkeypatch.setattr(mlp_module.AdaptiveMLP, "_train", train_scripted)


def test_a_configuration_far_above_its_layer_best_gets_a_second_start(monkeypatch):
    """(3,) lands in a poor local minimum (10× the error of (2,)): one more start, and the
    better one counts, so the layer goes on to (4,) and (5,)."""
    scripted_search(monkeypatch, {(1,): [1.0], (2,): [0.5], (3,): [5.0, 0.3], (4,): [0.2],
                                  (5,): [0.1], (6,): [0.15]})
    uv, xyz = paraboloid(200)
    model = AdaptiveMLP(max_layers=1, max_neurons=6, near_best=0, neuron_patience=1,
                        final_epochs=2, random_state=0).fit(uv, xyz)
    searched = [(h["layers"], h.get("retry", False)) for h in model.history_ if "final" not in h]
    assert searched == [((1,), False), ((2,), False), ((3,), False), ((3,), True),
                        ((4,), False), ((5,), False), ((6,), False)]
    assert model.hidden_layers_ == (5,)
    with pytest.raises(InvalidInputError, match="retry_factor"):
        AdaptiveMLP(retry_factor=1.0).fit(uv, xyz)


@pytest.mark.parametrize(("near_best", "chosen"), [(0.0, (3,)), (1.0, (5,))])
def test_of_the_configurations_near_the_lowest_error_the_largest_is_chosen(
    monkeypatch, near_best, chosen
):
    """(3,), (4,) and (5,) are within 10 % of each other, less than one standard error of an
    MSE on the 20 test samples (32 %): their differences are the noise."""
    scripted_search(monkeypatch, {(1,): [1.0], (2,): [0.5], (3,): [0.1], (4,): [0.105],
                                  (5,): [0.11], (6,): [0.2]})
    uv, xyz = paraboloid(200)
    model = AdaptiveMLP(max_layers=1, max_neurons=6, near_best=near_best, final_epochs=2,
                        random_state=0).fit(uv, xyz)
    assert model.hidden_layers_ == chosen
    with pytest.raises(InvalidInputError, match="near_best"):
        AdaptiveMLP(near_best=-1).fit(uv, xyz)


def test_training_early_stops_and_keeps_the_best_validation_weights():
    """One `_train` call: the net comes back with its own storage, at the weights of its best
    validation error, and stops after `patience` epochs without improvement."""
    from reconstruct.networks import build as _build
    from reconstruct.networks import mse as _mse

    uv, xyz = paraboloid(400, sigma=0.5)
    mlp = AdaptiveMLP(max_epochs=60, patience=2, random_state=0)
    mlp._check_params()
    rng, generator = mlp._random()
    tensors = mlp._samples(uv, xyz, rng, new_normalisation=True)
    net = _build((12,), "tanh", 2, 3, generator)
    record = mlp._train(net, tensors)
    params = list(net.parameters())
    assert all(p.grad is None for p in params)
    pointers = {p.untyped_storage().data_ptr() for p in params}
    assert len(pointers) == len(params)  # no longer views of one flat buffer
    assert 2 < record["epochs"] < 60  # the noise floor stops it well before the limit
    assert _mse(net, *tensors["validation"]) == pytest.approx(record["validation_mse"], rel=1e-12)


def test_training_does_not_import_torch_dynamo():
    """torch.optim's optimizers import torch._dynamo on first use (1.2 s here); ours don't."""
    import subprocess
    import sys

    code = (
        "import sys, numpy as np\n"
        "from reconstruct.mlp import AdaptiveMLP\n"
        "uv = np.random.default_rng(0).uniform(-1, 1, (200, 2))\n"
        "AdaptiveMLP(max_layers=1, max_neurons=2, final_epochs=3).fit(uv, np.c_[uv, uv.sum(1)])\n"
        "print('torch._dynamo' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def _hidden_weight_squares(model) -> float:
    from reconstruct.networks import linears

    return sum(float((layer.weight ** 2).sum()) for layer in linears(model.torch_model_)[:-1])


def test_weight_decay_shrinks_the_searched_final_fits_and_nothing_else():
    uv, xyz = paraboloid(400, sigma=0.05)
    plain = AdaptiveMLP(random_state=0, **SMALL).fit(uv, xyz)
    decayed = AdaptiveMLP(random_state=0, weight_decay=1.0, **SMALL).fit(uv, xyz)
    assert decayed.hidden_layers_ == plain.hidden_layers_  # the search does not see it
    searched = [r for r in plain.history_ if "final" not in r]
    assert [r["train_mse"] for r in searched] == [
        r["train_mse"] for r in decayed.history_ if "final" not in r]
    assert _hidden_weight_squares(decayed) < _hidden_weight_squares(plain)
    # given layers: no searched net to scale it by, so the same net
    given = dict(hidden_layers=(4,), final_epochs=20, random_state=0)
    np.testing.assert_array_equal(AdaptiveMLP(**given).fit(uv, xyz).predict(uv),
                                  AdaptiveMLP(weight_decay=1.0, **given).fit(uv, xyz).predict(uv))


@pytest.mark.parametrize("decay", [-0.1, float("nan")])
def test_a_negative_or_nan_weight_decay_is_refused(decay):
    uv, xyz = paraboloid(100)
    with pytest.raises(InvalidInputError, match="weight_decay"):
        AdaptiveMLP(weight_decay=decay, **SMALL).fit(uv, xyz)


def test_a_worker_trains_its_final_fit_with_the_same_weight_decay():
    from joblib.externals.loky import ProcessPoolExecutor

    uv, xyz = paraboloid(400, sigma=0.05)
    params = dict(random_state=0, weight_decay=1.0, **SMALL)
    here = AdaptiveMLP(**params).fit(uv, xyz)
    with ProcessPoolExecutor(max_workers=1) as pool:
        elsewhere = AdaptiveMLP(**params).search(uv, xyz).finish(pool, n_workers=1)
    np.testing.assert_array_equal(here.predict(uv), elsewhere.predict(uv))


def test_a_fit_on_more_samples_than_decay_up_to_trains_without_decay(monkeypatch):
    uv, xyz = paraboloid(400, sigma=0.05)
    monkeypatch.setattr("reconstruct.mlp.DECAY_UP_TO", 100)  # 340 training samples here
    plain = AdaptiveMLP(random_state=0, **SMALL).fit(uv, xyz)
    decayed = AdaptiveMLP(random_state=0, weight_decay=1.0, **SMALL).fit(uv, xyz)
    np.testing.assert_array_equal(plain.predict(uv), decayed.predict(uv))
