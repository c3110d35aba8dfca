"""Quality: measured features, statistical process control and run-to-run feedback (docs/quality.md).

recipe   a recipe's FEATURE and FEEDBACK lines
sheet    a run's own lines after its recipe: offsets, workpiece, tool (SETUP_RUN's `sheet`)
process  the simulated mill's process (bias, wear, shift, noise) and the parts it leaves for the CMM
spc      control charts, Western Electric rules, Cp and Cpk
feedback the EWMA run-to-run controller
store    the reads (sql/070_quality.sql)
lot      what a lot script uses: run sheets with offsets, verdicts, SPC alarms, TOOL_CHANGE
"""
