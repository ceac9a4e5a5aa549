"""Snakemake's name for SurfPhase's logger plugin (``snakemake --logger surfphase``).

Snakemake finds logger plugins as top-level packages named
``snakemake_logger_plugin_<name>``; the plugin itself is
:mod:`surfphase.runner.events`.
"""

from surfphase.runner.events import LogHandler, LogHandlerSettings

__all__ = ["LogHandler", "LogHandlerSettings"]
