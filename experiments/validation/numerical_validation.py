"""The I-RFT paper's numerical validation (Section V-A): Tables I and II and Fig. 5, rerun.

Data: simulated (the paper's configurations, the generic map). Run time: 9.3-9.6 s as irft reproduce; --quick 6 s.

    python experiments/validation/numerical_validation.py [--out experiments/results] [--quick]

Same as ``irft reproduce``; the study itself lives in ``irft_torch.studies`` so that the
installed command can run it.
"""

import sys

from irft_torch.cli import main

if __name__ == "__main__":
    sys.exit(main(["reproduce", *sys.argv[1:]]))
