"""Batches and sweeps: many seeded runs of one scenario, on local worker processes or on Dask.

A batch runs one scenario with N consecutive seeds; a sweep runs every point of a grid of
`--set section.key=v1,v2,...` overrides, each with N seeds. Every trial is a plain picklable
`TrialSpec` carrying its whole scenario TOML text, and runs in a worker through `run_trial`
(in-process mode: plant and controller in one thread, byte-identical to the process mode), which
never raises: a failing trial comes back with its status and error, and the others go on. Each
trial keeps its own run folder (`scenario.toml` as it ran, `summary.json`, logs, plots).

Invariant: `batch.json` depends only on the scenario, the seeds and the overrides, never on the
executor, the number of workers, the order in which trials finish or the wall clock (trials are
ordered by index, keys sorted, folders relative, wall times kept apart in `timing.json`); so a
batch run twice, or locally and on a Dask cluster, writes the same bytes.

The modules, in the order a batch goes through them: `planning` (the --set options and the
checked plan of trials; `tomlwrite` writes each trial's scenario), `runner` (the batch's folder
and its run), `trial` (one trial in a worker), `local` and `cluster` (the workers: local
processes, or a Dask cluster's), `reporting` (batch.json's content and batch.png).
"""
