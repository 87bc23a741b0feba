"""Saves that never leave a damaged file (irft_torch._files): a full disk, a file-size limit, an error or
Ctrl-C while writing leaves the previous model or dataset loadable and no temporary behind;
/dev/full and a folder are clear errors; files that must change together change together."""

import errno
import os
import subprocess
import sys
import textwrap

import pytest
import torch

import irft_torch as irft
from irft_torch._files import SaveError, StagedFiles, atomic_write
from irft_torch.data import Dataset, load_dataset, save_dataset


@pytest.fixture(scope="module")
def models():
    torch.set_default_dtype(torch.float64)
    c = irft.rft.contacts(irft.rft.CToe(0.02, 0.008), irft.rft.rectangle_path(n_steps=60))
    f = irft.rft.forces(irft.rft.FourierStressMap.generic(), c)
    small = irft.InverseRFT(c, f, method="observations", hyper_posterior="map", li_basis=False)
    c2 = irft.rft.contacts(irft.rft.CToe(0.02, 0.008), irft.rft.rectangle_path(n_steps=400))
    big = irft.InverseRFT(c2, irft.rft.forces(irft.rft.FourierStressMap.generic(), c2), method="observations",
                          hyper_posterior="map", li_basis=False)
    return small, big


def _no_temporaries(folder):
    return not [p for p in folder.iterdir() if ".tmp" in p.name]


def _save_half_then_fail(monkeypatch, failure):
    """torch.save writes the whole file, cuts it to half and raises ``failure`` (a disk filling up, a Ctrl-C)."""
    real = torch.save

    def half_then_fail(obj, fh, *a, **k):
        real(obj, fh, *a, **k)
        fh.truncate(fh.tell() // 2)
        raise failure

    monkeypatch.setattr(torch, "save", half_then_fail)


@pytest.mark.parametrize("failure", [OSError(errno.ENOSPC, "No space left on device"), KeyboardInterrupt()],
                         ids=["disk-full", "ctrl-c"])
def test_a_failed_save_leaves_the_previous_model_loadable(tmp_path, models, monkeypatch, failure):
    """(was: InverseRFT.save wrote in place: a full disk or Ctrl-C during a rewrite left an unreadable
    model.pt) the writer fails halfway through the new file: the old one loads with its own data."""
    small, big = models
    path = tmp_path / "model.pt"
    small.save(path)
    before = path.read_bytes()
    _save_half_then_fail(monkeypatch, failure)
    with pytest.raises(type(failure)) as e:
        big.save(path)
    if isinstance(failure, OSError):
        assert str(e.value) == (f"cannot save the model to {path}: No space left on device (the previous file, if "
                                "any, is unchanged)")
    monkeypatch.undo()
    assert path.read_bytes() == before and _no_temporaries(tmp_path)
    assert len(irft.InverseRFT.load(path).train_contacts) == len(small.train_contacts)


def test_a_failed_3d_save_leaves_the_previous_model_loadable(tmp_path, monkeypatch):
    """(was: InverseRFT3D.save wrote with torch.save in place: Ctrl-C or a full disk during a rewrite left a
    truncated, unreadable file) the same failure halfway through: the old 3-D model loads with its own data, and
    a folder is a clear error."""
    from gp.test_inverse3d import turning_toe

    c, f = turning_toe(T=8)
    small = irft.InverseRFT(c[:4], f[:4], hyper_posterior="map")
    big = irft.InverseRFT(c, f, hyper_posterior="map")
    path = tmp_path / "m3.pt"
    small.save(path)
    before = path.read_bytes()
    _save_half_then_fail(monkeypatch, OSError(errno.ENOSPC, "No space left on device"))
    with pytest.raises(OSError, match="cannot save the model to .*the previous file, if any, is unchanged"):
        big.save(path)
    monkeypatch.undo()
    assert path.read_bytes() == before and _no_temporaries(tmp_path)
    assert len(irft.InverseRFT.load(path).train_contacts) == 4
    with pytest.raises(SaveError, match="it is a folder; give a file name"):
        small.save(tmp_path)


def test_a_file_size_limit_leaves_the_previous_model_loadable(tmp_path, models):
    """ulimit -f (RLIMIT_FSIZE) below the new file's size, in a process of its own: the save fails with
    'File too large' and the old model still loads."""
    small, big = models
    small.save(tmp_path / "model.pt")
    big.save(tmp_path / "big.pt")
    limit = (tmp_path / "model.pt").stat().st_size + 4096
    assert (tmp_path / "big.pt").stat().st_size > limit
    code = textwrap.dedent(f"""
        import resource, sys
        import irft_torch as irft
        big = irft.InverseRFT.load({str(tmp_path / 'big.pt')!r})
        resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))
        try:
            big.save({str(tmp_path / 'model.pt')!r})
        except OSError as e:
            print(e)
            sys.exit(3)
    """)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 3 and "File too large" in r.stdout, r.stderr[-2000:]
    assert len(irft.InverseRFT.load(tmp_path / "model.pt").train_contacts) == len(small.train_contacts)
    assert _no_temporaries(tmp_path)


def test_special_paths_and_folders_are_clear_errors(tmp_path, models):
    """(was: raw torch errors) /dev/full says the disk is full; a folder says to give a file name."""
    small, _ = models
    if os.path.exists("/dev/full"):
        with pytest.raises(SaveError, match="cannot save the model to /dev/full: No space left on device"):
            small.save("/dev/full")
    with pytest.raises(SaveError, match="it is a folder; give a file name"):
        small.save(tmp_path)
    with pytest.raises(SaveError, match="there is no folder"):
        small.save(tmp_path / "missing" / "m.pt")


def test_a_failed_dataset_save_keeps_the_old_dataset(tmp_path, monkeypatch):
    import numpy as np

    c = irft.rft.contacts(irft.rft.IToe(0.02, 0.008), irft.rft.rectangle_path(n_steps=20))
    ds = Dataset(c, torch.ones(len(c), 2), torch.arange(len(c)) * 0.01, torch.zeros(len(c), 2))
    path = save_dataset(tmp_path / "ds.npz", ds)
    monkeypatch.setattr(np, "savez", lambda fh, **k: (fh.write(b"PK\x03\x04half"), (_ for _ in ()).throw(
        OSError(errno.EFBIG, "File too large"))))
    with pytest.raises(OSError, match="cannot save the dataset .* File too large .* unchanged"):
        save_dataset(path, ds)
    monkeypatch.undo()
    assert len(load_dataset(path)) == len(c) and _no_temporaries(tmp_path)


def test_files_that_change_together(tmp_path):
    """StagedFiles: nothing changes before commit; an error before it leaves the folder as it was; a
    check that says no keeps the old set; a commit changes every file."""
    (tmp_path / "a").write_text("old a")
    (tmp_path / "b").write_text("old b")
    with pytest.raises(RuntimeError), StagedFiles(tmp_path) as s:
        s.path("a").write_text("new a")
        raise RuntimeError("drawing failed")
    assert (tmp_path / "a").read_text() == "old a" and _no_temporaries(tmp_path)
    with StagedFiles(tmp_path) as s:
        s.path("a").write_text("new a")
        s.path("b").write_text("new b")
        assert not s.commit(check=lambda: False)
    assert (tmp_path / "a").read_text() == "old a" and (tmp_path / "b").read_text() == "old b"
    with StagedFiles(tmp_path) as s:
        s.path("a").write_text("new a")
        s.path("b").write_text("new b")
        assert s.commit()
    assert (tmp_path / "a").read_text() == "new a" and (tmp_path / "b").read_text() == "new b"
    assert _no_temporaries(tmp_path)
    assert atomic_write(tmp_path / "c.txt", lambda fh: fh.write(b"x")).read_bytes() == b"x"


def test_a_dataset_keeps_each_sample_place_and_refuses_a_misshapen_one(tmp_path):
    import numpy as np

    c = irft.rft.contacts(irft.rft.IToe(0.02, 0.008), irft.rft.rectangle_path(n_steps=20))
    places = torch.stack([torch.linspace(0, 1, len(c)), torch.full((len(c),), 0.25)], -1).double()
    ds = Dataset(c, torch.ones(len(c), 2), torch.arange(len(c)) * 0.01, torch.zeros(len(c), 2), locations=places)
    back = load_dataset(save_dataset(tmp_path / "walk.npz", ds))
    assert torch.equal(back.locations, places)
    assert load_dataset(save_dataset(tmp_path / "plain.npz", Dataset(c, ds.forces, ds.time, ds.toe_position))) \
        .locations is None
    with pytest.raises(ValueError, match="locations"):
        save_dataset(tmp_path / "bad.npz", Dataset(c, ds.forces, ds.time, ds.toe_position, locations=places[:5]))
    # a file whose places do not match its samples is damaged, said so
    d = dict(np.load(tmp_path / "walk.npz"))
    d["locations"] = d["locations"][:-1]
    np.savez(tmp_path / "cut.npz", **d)
    with pytest.raises(ValueError, match="inconsistent array shapes"):
        load_dataset(tmp_path / "cut.npz")
