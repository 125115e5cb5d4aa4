"""report.html: a self-contained page (plotly.js inline, opens offline from file://) written next to
calibration.json by ``solve`` (rewritten by ``reconstruct``) and next to comparison.json by ``compare``.

It sits above the solver and the comparison (it reads a Solution and compare's results) and below the
CLI, which it never imports. ``results.write_results`` receives the writer as a callback, so the report
lands in the same staged, all-or-nothing output.
"""

from calib3r_graph.report.compare_page import compare_report_html
from calib3r_graph.report.solve_page import solve_report_html, solve_report_writer, write_result_report

__all__ = ["compare_report_html", "solve_report_html", "solve_report_writer", "write_result_report"]
