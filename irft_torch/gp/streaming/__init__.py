"""Learning while the data arrive, for many robots or environments at once: ``TerrainFilter`` (``filter``: B
independent I-RFT posteriors over sliding windows, one batched update per step; over the ground too, from a spatial
model), ``TerrainFilterMixture`` (``filter_mixture``: the same averaged over hyperparameter draws) and
``SpatialTiles`` (``tiles``: maps over the ground, one walk, at a bounded cost per step); ``window`` holds the
windows' bookkeeping."""
