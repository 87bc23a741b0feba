"""A fleet of datasets reduced to one set of spectral statistics on Dask (``studies.fleet``), against one
pass over the concatenated data (``gp.statistics.recording_statistics``); ``irft fit --dask`` against
``--jobs 1``. The clusters are in-process (``LocalCluster(processes=False)``): seconds, not minutes."""

import sys

import pytest
import torch

import irft_torch as irft
from irft_torch.data import Dataset, load_dataset, save_dataset
from irft_torch.gp.kernels.fourier import FourierBasis
from irft_torch.gp.statistics import recording_statistics, statistics_arrays
from irft_torch.rft import Contacts, FourierStressMap

distributed = pytest.importorskip("distributed", reason="Dask is an optional extra: pip install 'irft-torch[dask]'")

from irft_torch.studies.fleet import DASK_MISSING, reduce_on_dask  # noqa: E402


def recording(i: int, n: int = 240):
    toe = irft.rft.CToe(0.02, 0.008, n_segments=6)
    path = irft.rft.spline_path([(-0.2, 0.0), (-0.1, -0.03 - 0.005 * i), (0.1, -0.01), (0.2, 0.0)], n_steps=n)
    c = irft.rft.contacts(toe, path)
    f = irft.rft.forces(FourierStressMap.generic(0.45, 0.42), c)
    f = f + 0.01 * f.abs().amax(0) * torch.randn(f.shape, generator=torch.Generator().manual_seed(i), dtype=f.dtype)
    return c, f


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """Four dataset files: two without statistics, one with its own in a larger basis (cut down when read),
    one with statistics of other data (refused with a warning, recomputed)."""
    tmp = tmp_path_factory.mktemp("fleet")
    paths, cs, fs = [], [], []
    for i in range(4):
        c, f = recording(i)
        ds = Dataset(c, f, torch.arange(len(c), dtype=torch.float64), torch.zeros(len(c), 2))
        if i == 1:
            ds.statistics = statistics_arrays(recording_statistics(c, f, FourierBasis(9, 10)), c, f)
        if i == 3:
            c_other, f_other = recording(7)
            ds.statistics = statistics_arrays(recording_statistics(c_other, f_other), c_other, f_other)
        paths.append(str(save_dataset(tmp / f"run{i}.npz", ds)))
        cs.append(c)
        fs.append(f)
    return paths, Contacts.cat(cs), torch.cat(fs)


@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(processes=False, n_workers=2, threads_per_worker=1, dashboard_address=None) as c:
        yield c


def test_dask_reduction_equals_one_pass_over_the_concatenated_data(fleet, cluster):
    paths, c, f = fleet
    basis = FourierBasis(7, 8)
    with distributed.Client(cluster) as client, pytest.warns(UserWarning, match="do not belong"):
        r = reduce_on_dask(paths, basis, client=client)
    one = recording_statistics(c, f, basis)
    assert (r.n_datasets, r.n_from_files, r.n_workers) == (4, 1, 2)
    assert r.statistics.n == one.n == len(f) and r.statistics.meta == one.meta
    for k in ("P", "b", "yy", "bg", "yg", "gg"):
        a, b = getattr(r.statistics, k), getattr(one, k)
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12 * float(b.abs().max()), msg=k)
    with distributed.Client(cluster) as client:  # by address, as `irft fit --dask ADDRESS` connects
        again = reduce_on_dask(paths[:1], basis, address=cluster.scheduler_address)
        assert client.status == "running"
    torch.testing.assert_close(again.statistics.P, recording_statistics(*recording(0), basis).P, rtol=1e-12, atol=0)


def test_missing_dask_is_a_clear_error(monkeypatch, fleet):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed now raises ImportError
    with pytest.raises(ImportError, match=r"irft-torch\[dask\]"):
        reduce_on_dask(fleet[0])
    from irft_torch.cli import main

    assert main(["fit", *fleet[0], "--method", "spectral", "--dask"]) == 2  # one line naming --dask, no traceback
    assert "dask" in DASK_MISSING


def test_irft_fit_with_dask_equals_jobs_1(fleet, cluster, tmp_path, capsys):
    from irft_torch.cli import main

    paths = fleet[0]
    maps, outs = [], []
    for name, extra in (("jobs", ["--jobs", "1"]), ("dask", ["--dask", cluster.scheduler_address])):
        out = tmp_path / name
        assert main(["fit", *paths, "--method", "spectral", "--n-iter", "15", "--out", str(out), "--no-progress",
                     "--hyper-posterior", "map", "--no-li-basis", *extra]) == 0  # the reduction, not the posterior
        said = capsys.readouterr()
        assert "do not belong" in said.err  # the CLI says its warnings on stderr (one line each)
        outs.append(said.out)
        model = irft.InverseRFT.load(out / "model.pt")
        g = torch.linspace(-1.4, 1.4, 15, dtype=torch.float64)
        maps.append(model.stress_map(*torch.meshgrid(g, g, indexing="ij")))
    assert "1 read from the files, 3 computed on the Dask cluster at" in outs[-1]
    jobs, dask = maps
    span = (jobs.mean.amax((0, 1)) - jobs.mean.amin((0, 1))).max()
    assert float((dask.mean - jobs.mean).abs().max()) <= 1e-8 * float(span)
    assert float((dask.variance - jobs.variance).abs().max()) <= 1e-8 * float(jobs.variance.max())
    assert len(load_dataset(paths[0])) == 240


def test_bad_dask_arguments(fleet, capsys):
    from irft_torch.cli import main

    paths = fleet[0]
    assert main(["fit", "--dask", *paths]) == 2  # the first dataset taken as the address
    assert "--dask" in capsys.readouterr().err
    assert main(["fit", *paths, "--jobs", "2", "--dask"]) == 2
    assert "--jobs" in capsys.readouterr().err
    with pytest.raises(ValueError, match="paths"):
        reduce_on_dask([])
