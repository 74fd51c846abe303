"""`pdtool batch`: many bake/fit jobs from one TOML file, on a local process pool or a Ray cluster.

A job is a pdtool command line. The frontend that offers batch hands in `CommandLines`: how
to parse a command line and how to run one in-process. `pdtool batch` hands in its own click
commands, so a batch job and a typed command take one code path (same option checks, same
defaults, same atomic outputs, same one-line errors) while this scheduler imports no
frontend. It only decides *when* and *where* a job runs:

- jobs file (jobs.py): `[[job]]` tables, sweeps expanded into a cartesian product, `after`
  edges;
- inputs and outputs (files.py): what each job reads and writes, and fingerprints: sha256
  over the job's command line and the bytes of every input file it names, kept in a small
  `<output>.batch.json` record beside the job's main output so that `--resume` skips the
  jobs that are already done with the same inputs;
- workers (workers.py): `run_job`, and the backends `LocalBackend` (spawned processes, one
  per CPU worker plus one per visible GPU) and `RayBackend` (one Ray task per job,
  `num_gpus=1` when the job runs on CUDA);
- the scheduler (run.py): `run_batch`, `BatchResult` and the summary.

A jobs file is data from anywhere: it is size- and depth-limited before it is parsed, its
templates are plain `{name}` substitutions, its outputs stay inside its own folder unless
the caller allows otherwise, and workers stop with the driver (see docs/batch.md).
"""
# torch, ray and tqdm are imported inside the functions that use them (workers.py, run.py),
# not here: the batch driver process stays light, and only workers load torch and warp.
from pd_tool.batch.files import (
    MAX_INPUT_FILES,
    RECORD_SUFFIX,
    CommandLines,
    JobFiles,
    canonical,
    check_outputs,
    clash,
    file_digest,
    fingerprint,
    is_up_to_date,
    job_files,
    outside,
    record_path,
    remove_temporaries,
    temporaries,
    write_record,
)
from pd_tool.batch.jobs import (
    COMMANDS,
    HELP_ARGS,
    MAX_ARG_CHARS,
    MAX_ARGS,
    MAX_DEPTH,
    MAX_EDGES,
    MAX_FILE_BYTES,
    MAX_JOBS,
    MAX_LINE_CHARS,
    MAX_NAME_CHARS,
    MAX_TOTAL_ARG_CHARS,
    Job,
    JobsFileError,
    asks_for_help,
    load_jobs,
    parse_jobs,
    slug,
)
from pd_tool.batch.run import (
    BLOCKED,
    FAILED,
    OK,
    UP_TO_DATE,
    BatchInterrupted,
    BatchResult,
    JobResult,
    run_batch,
    write_summary,
)
from pd_tool.batch.workers import (
    STOP_GRACE_S,
    LocalBackend,
    RayBackend,
    WorkerStopped,
    count_gpus,
    ray_resources,
    run_job,
    stop_processes,
)

__all__ = [
    "BLOCKED",
    "COMMANDS",
    "FAILED",
    "HELP_ARGS",
    "MAX_ARGS",
    "MAX_ARG_CHARS",
    "MAX_DEPTH",
    "MAX_EDGES",
    "MAX_FILE_BYTES",
    "MAX_INPUT_FILES",
    "MAX_JOBS",
    "MAX_LINE_CHARS",
    "MAX_NAME_CHARS",
    "MAX_TOTAL_ARG_CHARS",
    "OK",
    "RECORD_SUFFIX",
    "STOP_GRACE_S",
    "UP_TO_DATE",
    "BatchInterrupted",
    "BatchResult",
    "CommandLines",
    "Job",
    "JobFiles",
    "JobResult",
    "JobsFileError",
    "LocalBackend",
    "RayBackend",
    "WorkerStopped",
    "asks_for_help",
    "canonical",
    "check_outputs",
    "clash",
    "count_gpus",
    "file_digest",
    "fingerprint",
    "is_up_to_date",
    "job_files",
    "load_jobs",
    "outside",
    "parse_jobs",
    "ray_resources",
    "record_path",
    "remove_temporaries",
    "run_batch",
    "run_job",
    "slug",
    "stop_processes",
    "temporaries",
    "write_record",
    "write_summary",
]
