"""`cubecloud preprocess`: a scan -> the normalized S³ cube volume in WORK/preprocess/."""

from cubecloud_cli.core.lazy import lazy_exports

_EXPORTS = {
    "PreprocessSettings": "settings",
    "preprocess_scan": "stage",
}
__getattr__ = lazy_exports(__name__, _EXPORTS)

__all__ = ["PreprocessSettings", "preprocess_scan"]
