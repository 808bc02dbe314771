"""The run report: ``report.html`` + ``report.png`` built from a run directory's files only.

``build`` writes the two files (:func:`~splat_slam_ros.report.build.write_report`), ``run_record``
reads a run directory back, ``page`` lays out the HTML page, ``plots`` draws its figures and
image tiles, and ``recording`` holds what a run records for its report while it runs (the
configuration used, the warnings logged).
"""
