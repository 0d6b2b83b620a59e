"""Raw frame to stars to attitude: frame model and readers, detection, centroid and colour fit, camera model, optics search, the pipeline run."""
