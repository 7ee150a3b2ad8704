"""Transfer functions: which tissue a scan value shows, and how opaque it is. One definition
serves the volume renderer (``render/``), the export's presets and the scalar Gaussians that
apply a transfer function at view time (``splat/``, ``view/``)."""
