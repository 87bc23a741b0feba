"""Studies built on the library, above ``gp``, ``design``, ``data`` and ``hardware``: the paper's
numerical study (``studies.reproduce``: settings, configurations and fits, handed back as results),
its report (``studies.report``: tables, figures and report.md read from those results), both run
by ``studies.paper_study.run_study`` (``irft reproduce``); the calibration harness
(``studies.calibration``); process pools for many small fits (``studies.workers``)."""
