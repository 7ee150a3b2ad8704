"""`cubecloud preprocess`: a scan -> the normalized S³ cube volume in WORK/preprocess/."""

from cubecloud_cli.preprocess.settings import PreprocessSettings
from cubecloud_cli.preprocess.stage import preprocess_scan

__all__ = ["PreprocessSettings", "preprocess_scan"]
