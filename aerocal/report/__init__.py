"""The flight report: figures (:mod:`aerocal.report.figures`), the figures of a processed flight from its
step outputs (:mod:`aerocal.report.flight_figures`) and the self-contained HTML (:mod:`aerocal.report.html`)."""

from aerocal.report.figures import (
    Figure,
    block_figure,
    dem_difference_figure,
    image_residual_figure,
    io_at_temperatures,
    temperature_io_figure,
)
from aerocal.report.flight_figures import (
    FigureSkipped,
    dem_difference_for_flight,
    image_residuals_from_assessment,
    temperature_io_for_flight,
)
from aerocal.report.html import CertificateTable, write_report

__all__ = [
    "CertificateTable", "Figure", "FigureSkipped", "block_figure", "dem_difference_figure",
    "dem_difference_for_flight", "image_residual_figure", "image_residuals_from_assessment",
    "io_at_temperatures", "temperature_io_figure", "temperature_io_for_flight", "write_report",
]
