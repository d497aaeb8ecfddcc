"""Teaching: exercises, the live task state, metrics per task and session, and reports.

Everything here reads what the console and the renderer recorded in the ledger (the
`view` records of each image's geometry, the `trainee` and `exercise_*` records), so a
report can be made again, on another machine, from the ledger alone.
"""
