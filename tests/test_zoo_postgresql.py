"""
RL Zoo's distributed hyper-parameter search on a real PostgreSQL server: two ``-optimize`` workers share one study
through ``--storage postgresql://...``, one is killed in the middle of a trial, and the other completes the study
with the killed trial marked FAIL (Optuna's trial heartbeat), not RUNNING forever.

Both workers start at once on a new database, as a job scheduler starts them: one creates Optuna's tables, the other
waits for them.

It takes about a minute, so it runs only with ``SB3_DACERF_TEST_POSTGRESQL=1``:

    SB3_DACERF_TEST_POSTGRESQL=1 python -m pytest tests/test_zoo_postgresql.py

The server is a throw-away cluster (``initdb`` in a temporary folder, listening on 127.0.0.1 only, on a free port),
started from the PostgreSQL server binaries (Debian: ``apt-get install postgresql``) and removed afterwards. Without
them, or without a PostgreSQL driver for SQLAlchemy (``psycopg``), the test is skipped.
"""

import glob
import os
import pwd
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

optuna = pytest.importorskip("optuna")
pytest.importorskip("rl_zoo3")
sqlalchemy = pytest.importorskip("sqlalchemy")

from test_zoo import zoo_command  # noqa: E402

try:  # SQLAlchemy's driver for postgresql:// URLs (psycopg 3 from SQLAlchemy 2.1 on, psycopg2 before)
    sqlalchemy.create_engine("postgresql://localhost/postgres").dispose()
except ImportError as error:
    pytest.skip(f"no PostgreSQL driver for SQLAlchemy (pip install 'psycopg[binary]'): {error}", allow_module_level=True)

SERVER_BINARIES = ("initdb", "pg_ctl")
OPT_IN = "SB3_DACERF_TEST_POSTGRESQL"


def server_bin_dir() -> Path | None:
    """Folder of the PostgreSQL server binaries: on the PATH, or Debian's /usr/lib/postgresql/<version>/bin."""
    found = shutil.which("initdb")
    if found:
        return Path(found).parent
    candidates = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda path: int(Path(path).parts[-3]))
    return Path(candidates[-1]).parent if candidates else None


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def postgresql_url() -> Iterator[str]:
    if os.environ.get(OPT_IN) != "1":
        pytest.skip(f"about a minute with two RL Zoo workers: run it with {OPT_IN}=1")
    bin_dir = server_bin_dir()
    if bin_dir is None or not all((bin_dir / name).is_file() for name in SERVER_BINARIES):
        pytest.skip("PostgreSQL server binaries not found (Debian: apt-get install postgresql)")
    # The server refuses to run as root: as root, run it as the `postgres` user that Debian's package creates
    run_as: list[str] = []
    if os.geteuid() == 0:
        try:
            user = pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root and there is no `postgres` user to run the PostgreSQL server as")
        run_as = ["runuser", "-u", "postgres", "--"]
    folder = Path(tempfile.mkdtemp(prefix="sb3-dacerf-postgresql-"))
    if run_as:
        os.chown(folder, user.pw_uid, user.pw_gid)
    data, port = folder / "data", free_port()

    def run(*command: str) -> None:
        result = subprocess.run([*run_as, *command], capture_output=True, text=True, timeout=120)
        assert result.returncode == 0, f"{' '.join(command)}\n{result.stdout}\n{result.stderr}"

    try:
        run(str(bin_dir / "initdb"), "-D", str(data), "-U", "postgres", "--auth=trust", "--no-sync", "-E", "UTF8")
        server_options = f"-c listen_addresses=127.0.0.1 -p {port} -k {folder} -c fsync=off"
        run(str(bin_dir / "pg_ctl"), "-D", str(data), "-o", server_options, "-l", str(folder / "server.log"), "-w", "start")
        try:
            yield f"postgresql://postgres@127.0.0.1:{port}/postgres"
        finally:
            run(str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "immediate", "-w", "stop")
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def wait_for(condition, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out after {timeout} s waiting for {what}"
        time.sleep(0.2)


def test_killed_worker_trial_is_failed_and_the_study_completes(tmp_path, postgresql_url):
    study_name = "dacerf-postgresql"
    states = optuna.trial.TrialState

    def trials() -> list:
        try:
            return optuna.load_study(study_name=study_name, storage=postgresql_url).get_trials(deepcopy=False)
        except KeyError:  # the study is not created yet
            return []

    def worker(name: str, timesteps: int, n_trials: int) -> subprocess.Popen:
        command, env = zoo_command(
            "train",
            *["--algo", "dacerf", "--env", "Pendulum-v1", "-n", str(timesteps), "--num-threads", "1", "--optimize"],
            *["--storage", postgresql_url, "--study-name", study_name, "--n-trials", str(n_trials)],
            *["--n-evaluations", "1", "--eval-episodes", "1", "--sampler", "random", "--pruner", "none"],
            *["--no-optim-plots", "-f", "logs", "-uuid", "-params", "learning_starts:50"],
            *["policy_kwargs:dict(optimizer_class='RAD')", "--optimization-log-path", name],
        )
        # heartbeat every second: a trial without one for 2 s is stale
        env = {**env, "SB3_DACERF_OPTUNA_HEARTBEAT": "1"}
        return subprocess.Popen(
            command, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
        )

    def started_trials(name: str) -> list[int]:
        """Numbers of the trials a worker has started training (RL Zoo makes <optimization log path>/trial_<number>)."""
        return [int(path.name.removeprefix("trial_")) for path in (tmp_path / name).glob("trial_*")]

    # Worker A's trial is long (5,000 steps), so it is surely still running when A is killed; B's are short
    worker_a, worker_b = worker("worker_a", 5_000, 1), worker("worker_b", 60, 5)
    try:
        wait_for(lambda: started_trials("worker_a") and started_trials("worker_b"), 180, "both workers to train a trial")
        (killed_trial,) = started_trials("worker_a")
        assert optuna.load_study(study_name=study_name, storage=postgresql_url).trials[killed_trial].state == states.RUNNING
    except BaseException as error:
        for process in (worker_a, worker_b):
            os.killpg(process.pid, signal.SIGKILL)
        raise AssertionError(
            f"worker A:\n{worker_a.communicate()[0][-3000:]}\nworker B:\n{worker_b.communicate()[0][-3000:]}"
        ) from error
    os.killpg(worker_a.pid, signal.SIGKILL)  # no clean-up: as a node lost with its machine
    worker_a.communicate()

    output, _ = worker_b.communicate(timeout=300)
    assert worker_b.returncode == 0, output[-3000:]

    final = {trial.number: trial.state for trial in trials()}
    assert final[killed_trial] == states.FAIL
    # B completed its 5 trials; the killed one was marked FAIL when B started a trial 2 s after A's last heartbeat
    assert sorted(state for number, state in final.items() if number != killed_trial) == [states.COMPLETE] * 5
    assert states.RUNNING not in final.values()
