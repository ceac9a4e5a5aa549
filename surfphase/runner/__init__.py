"""What ``surfphase run`` and ``surfphase status`` do, apart from their command lines
(:mod:`surfphase.commands.run`).

- :mod:`~surfphase.runner.locate`: the workflow, the campaign folder, its config, the
  Snakemake command and the campaign's SLURM profile;
- :mod:`~surfphase.runner.status`: per session and stage, done / failed / outdated /
  pending, from Snakemake's ``--detailed-summary``;
- :mod:`~surfphase.runner.locks`: a live run or a killed one's stale lock;
- :mod:`~surfphase.runner.events`: Snakemake's job events as JSON lines (a logger
  plugin, ``snakemake --logger surfphase``) and their reader;
- :mod:`~surfphase.runner.progress`: the run's progress lines, from those events;
- :mod:`~surfphase.runner.partial`: the campaign table and page when some sessions
  failed.

Nothing here imports more than the standard library, PyYAML and Snakemake's plugin
interface at module level (Snakemake imports the logger plugin at every start).
"""
