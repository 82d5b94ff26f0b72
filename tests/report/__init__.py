"""report/: report.html."""
