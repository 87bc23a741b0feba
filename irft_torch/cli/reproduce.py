"""``irft reproduce``: rerun the paper's numerical study (``studies.paper_study.run_study``) and write
its tables, figures and report.md."""

from __future__ import annotations

from .arguments import UsageError, _out_dir

PRELOAD = ("irft_torch.studies.paper_study",)  # what the study's worker processes import: studies.paper_study.PRELOAD


def cmd_reproduce(a) -> int:
    from dataclasses import replace

    from ..studies.paper_study import run_study
    from ..studies.reproduce import StudySettings
    from ..studies.workers import default_workers

    _out_dir(a.out, "--out")  # before the study: a bad --out fails now
    settings = StudySettings.quick_settings() if a.quick else StudySettings()
    if a.priors == "none":  # the paper's plain marginal likelihood for every fit
        settings = replace(settings, priors=None)
    if a.li_basis or a.generic_shape:
        settings = replace(settings, li_basis=True, generic_shape=a.generic_shape)
    if a.hyper_posterior != "map":
        settings = replace(settings, hyper_posterior=a.hyper_posterior)
    if a.jobs < 0:
        raise UsageError("--jobs", f"must be 0 (one per CPU) or a positive number of processes, got {a.jobs}")
    workers = default_workers() if a.jobs == 0 else a.jobs
    if a.device != "cpu":
        import torch

        try:
            dev = torch.device(a.device)
        except RuntimeError as e:
            raise UsageError("--device", f"{a.device!r} is not a torch device ({e})") from None
        if dev.type == "cuda" and not torch.cuda.is_available():
            raise UsageError("--device", f"{a.device!r}: no CUDA device is visible here (torch "
                                         f"{torch.__version__}); leave --device out to fit on the CPU")
        settings = replace(settings, device=str(dev))
        workers = 1  # one process drives the GPU (the fits are batched there by gp.fit_together)
    r = run_study(a.out, settings, progress=not a.no_progress, workers=workers)
    print(f"wrote tables, figures and report.md to {r['out_dir']}/ in {r['elapsed_s']:.0f} s")
    return 0


def register(sub) -> None:
    p = sub.add_parser("reproduce", help="rerun the paper's numerical validation (Tables I, II, Fig. 5)",
                       description="Rerun the I-RFT paper's simulation study: four toe/gait configurations, "
                                   "zero vs physics prior mean, the noise study; write table1.csv, "
                                   "table2.csv, figures and report.md.")
    p.add_argument("--out", default="experiments/results", help="output directory (default experiments/results)")
    p.add_argument("--quick", action="store_true", help="smaller grid, fewer steps and seeds (< 1 minute)")
    p.add_argument("--jobs", type=int, default=0,
                   help="worker processes for the fits (default 0: one per CPU, at most 8; 1: this process)")
    p.add_argument("--priors", choices=["physical", "none"], default="physical",
                   help="hyperparameter priors of every fit: the library's physical priors (MAP, default) or none "
                        "(the paper's plain marginal likelihood; its Table I rows are in every run)")
    p.add_argument("--li-basis", action="store_true",
                   help="fit every model with Li et al.'s basis as a kernel term (InverseRFT's default, "
                        "MapPrior(kernel='li'); "
                        "docs/calibration.md); the paper's kernel is the RBF alone")
    p.add_argument("--generic-shape", action="store_true",
                   help="also give Li et al.'s generic map an uncertain scale of its own (InverseRFT(..., "
                        "prior=MapPrior(kernel='li+generic')); implies --li-basis)")
    p.add_argument("--hyper-posterior", choices=["map", "laplace"], default="map",
                   help="map (the paper's plug-in, default) or laplace (predict with the hyperparameter posterior); "
                        "with --li-basis: the library's default fit, InverseRFT(contacts, forces)")
    p.add_argument("--device", default="cpu",
                   help="where the models are fitted: cpu (default) or cuda[:N] (one process; needs a CUDA build "
                        "of torch); the data, metrics and figures stay on the CPU")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_reproduce)
