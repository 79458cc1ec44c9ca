"""The Gaussian smoothers check every field of the filter result they are handed (a
Gaussian-smoother trial: only the means were checked; covariances one step short had been
read a step late, 0.14 off, integer predicted means truncated, 0.78 off, NaN run to NaN
means, other runs and singular predicted covariances failed in torch)."""

import dataclasses

import pytest
import torch

import difffilter as df

F64 = torch.float64


@pytest.fixture(scope="module")
def case():
    F = torch.tensor([[0.9, 0.2], [-0.1, 0.8]], dtype=F64)
    eye = torch.eye(2, dtype=F64)
    model = df.LinearGaussianModel(F, torch.tensor([[1.0, 0.0]], dtype=F64), 0.3 * eye,
                                   torch.tensor([[0.5]], dtype=F64), torch.zeros(2, dtype=F64),
                                   eye)  # fmt: skip
    _, ys, _ = model.simulate(6, (3,), generator=torch.Generator().manual_seed(0))
    return model, df.kalman_filter(model, ys), df.unscented_kalman_filter(model, ys)


def _edits(result):
    def at(name, index, value):
        t = getattr(result, name).clone()
        t[index] = value
        return t

    covs = result.covs.expand(3, *result.covs.shape[-3:]).clone()
    indefinite = covs.clone()
    indefinite[0, 2] = -indefinite[0, 2]
    asymmetric = covs.clone()
    asymmetric[0, 2, 0, 1] += 0.3
    pred = result.pred_covs.expand(3, *result.pred_covs.shape[-3:]).clone()
    singular = pred.clone()
    singular[0, 2] = 0.0
    return {
        "covs one step short": ("covs", covs[:, 1:], "filtered.covs must be"),
        "pred_means one step short": ("pred_means", result.pred_means[:, :-1],
                                      "filtered.pred_means must be"),
        "integer pred_means": ("pred_means", result.pred_means.round().long(),
                               "filtered.pred_means is torch.int64"),
        "float32 covs": ("covs", covs.float(), "filtered.covs is torch.float32"),
        "NaN mean": ("means", at("means", (1, 3, 0), float("nan")), "filtered.means contains NaN"),
        "NaN pred_covs": ("pred_covs", pred.index_put((torch.tensor(1), torch.tensor(3)),
                          torch.full((2, 2), float("nan"), dtype=F64)), "filtered.pred_covs contains"),
        "covs of other runs": ("covs", covs[:2], "filtered.covs holds the runs"),
        "asymmetric covs": ("covs", asymmetric, "filtered.covs must be symmetric"),
        "indefinite covs": ("covs", indefinite, "filtered.covs"),
        "singular pred_covs": ("pred_covs", singular, "filtered.pred_covs"),
    }  # fmt: skip


EDITS = ["covs one step short", "pred_means one step short", "integer pred_means",
         "float32 covs", "NaN mean", "NaN pred_covs", "covs of other runs", "asymmetric covs",
         "indefinite covs", "singular pred_covs"]  # fmt: skip


@pytest.mark.parametrize("edit", EDITS)
def test_a_field_edited_by_hand_is_named(case, edit):
    model, kf, ukf = case
    for result, smoother in ((kf, df.rts_smoother), (ukf, df.unscented_rts_smoother)):
        name, value, words = _edits(result)[edit]
        with pytest.raises(ValueError, match=words.replace(".", r"\.")):
            smoother(model, dataclasses.replace(result, **{name: value}))


def test_a_filters_own_result_still_smooths_to_the_dense_answer(case):
    model, kf, ukf = case
    exact = df.rts_smoother(model, kf)
    torch.testing.assert_close(df.unscented_rts_smoother(model, ukf).means, exact.means)
