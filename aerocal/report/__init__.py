"""The flight report: figures (:mod:`aerocal.report.figures`), the figures of a processed flight from its
step outputs (:mod:`aerocal.report.flight_figures`), the words a reader sees (:mod:`aerocal.report.wording`),
the page rendered from Jinja2 templates (:mod:`aerocal.report.html`, ``templates/``) and the report of a
processed flight (:func:`aerocal.report.flight_report.write_flight_report`).

Tests: tests/test_report.py.
"""

from aerocal.report.figures import (
    Figure,
    block_figure,
    dem_difference_figure,
    distortion_figure,
    image_residual_figure,
    io_at_temperatures,
    overview_figure,
    temperature_io_figure,
    tie_point_figure,
)
from aerocal.report.flight_figures import (
    FigureSkipped,
    dem_difference_for_flight,
    image_residuals_from_assessment,
    overlap_counts,
    temperature_io_for_flight,
)
from aerocal.report.flight_report import write_flight_report
from aerocal.report.html import CertificateTable, write_report

__all__ = [
    "CertificateTable", "Figure", "FigureSkipped", "block_figure", "dem_difference_figure",
    "dem_difference_for_flight", "distortion_figure", "image_residual_figure", "image_residuals_from_assessment",
    "io_at_temperatures", "overlap_counts", "overview_figure", "temperature_io_figure", "temperature_io_for_flight",
    "tie_point_figure", "write_flight_report", "write_report",
]
