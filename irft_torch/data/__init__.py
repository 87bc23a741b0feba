"""Data: the dataset file format (``Dataset``, ``save_dataset``, ``load_dataset``: what ``irft ingest``
and ``irft simulate`` write and ``irft fit`` reads) and readers of others' data sets that yield
contacts and forces: ``data.dem`` (DEM plate-intrusion runs) and ``data.wheel`` (rover-wheel runs).

A floor below ``gp`` and ``hardware`` (it imports only ``rft`` and ``metrics``), so the hardware
pipeline can build datasets. The Traveler leg's controller log stays in ``hardware.traveler``: it is
read through that leg's geometry and statics (``hardware.FiveBarLeg``), as the CAN logs are.
"""

from .dataset import STATISTICS_PREFIX, Dataset, dataset_summary, load_dataset, save_dataset

__all__ = ["Dataset", "dataset_summary", "save_dataset", "load_dataset", "STATISTICS_PREFIX"]
