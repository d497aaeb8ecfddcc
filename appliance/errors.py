"""The one exception a person's mistake turns into.

Anything a trainee, technician or admin can get wrong (a bad profile, a missing device, an
unreadable CT, a full disk) is raised as `FluorosimError` with one sentence that names the
file, field or device and says what to do. The command line prints it on one line and
exits 2; the daemon shows it on screen and keeps running. A traceback means a bug.
"""


class FluorosimError(Exception):
    """A one-line, actionable message for a problem a person can fix."""

    exit_code = 2
