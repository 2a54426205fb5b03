"""Process exit codes of the ``companion`` command, shared by the CLI, the daemon and the systemd unit."""

OK = 0
#: An unexpected internal error (a bug): the traceback is logged.
INTERNAL_ERROR = 1
#: Bad input on the command line: an unreadable file, an invalid config, a bad calibration. Not retried.
BAD_INPUT = 2
#: The service could not start (bad config, no camera after the timeout, no vehicle). The systemd unit
#: lists it in RestartPreventExitStatus so that it is not restarted in a loop.
STARTUP_FAILURE = 78  # EX_CONFIG from sysexits.h
#: A second SIGTERM/SIGINT forced the exit before the clean shutdown finished.
FORCED_EXIT = 130
