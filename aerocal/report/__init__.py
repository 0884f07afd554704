"""The flight report: figures (:mod:`aerocal.report.figures`) and the self-contained HTML
(:mod:`aerocal.report.html`)."""

from aerocal.report.figures import (
    Figure,
    block_figure,
    dem_difference_figure,
    image_residual_figure,
    temperature_io_figure,
)
from aerocal.report.html import CertificateTable, write_report

__all__ = [
    "CertificateTable", "Figure", "block_figure", "dem_difference_figure", "image_residual_figure",
    "temperature_io_figure", "write_report",
]
