"""Keeps robosuite's import-time advice (no private macro file, optional robots and IK it cannot load) out of
every process that imports our env, rollout workers included; its errors still show."""

import logging

# robosuite.utils.log_utils.DefaultLogger's name. A filter, not a level: robosuite sets the level to
# macros.CONSOLE_LOGGING_LEVEL when it creates the logger, after this module has run.
ROBOSUITE_LOGGER_NAME = "robosuite_logs"


def errors_only(record: logging.LogRecord) -> bool:
    return record.levelno >= logging.ERROR


logging.getLogger(ROBOSUITE_LOGGER_NAME).addFilter(errors_only)
