"""``sb3-hgrn tune`` workers sharing one study through a real database server: PostgreSQL and MariaDB
(MySQL's protocol, through the PyMySQL driver of ``mysql+pymysql://`` URLs).

Each fixture starts a throwaway server that listens on a Unix socket only, in a directory of its own;
the workers are separate ``sb3-hgrn tune`` processes, as on separate machines.
"""

import glob
import multiprocessing
import os
import pwd
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from sb3_hgrn.cli import main
from tests.test_tune import SPACE, TOY

STUDY = "shared"
# A quiet `tune` command at the `ci` budget, cut to two evaluations of one episode per trial.
WORKER = [sys.executable, "-m", "sb3_hgrn", "tune", *TOY, "--verbose", "0"]
WORKER += "--timesteps 300 --eval-freq 150 --eval-episodes 1 --env-param n_agents=5 --pruner none".split()


def postgres_binaries() -> tuple[str, str] | None:
    """``initdb`` and ``pg_ctl`` from ``PATH`` or the newest ``/usr/lib/postgresql/*/bin``; ``None``
    when no directory has both."""
    for path in [None, *sorted(glob.glob("/usr/lib/postgresql/*/bin"), reverse=True)]:
        initdb, pg_ctl = shutil.which("initdb", path=path), shutil.which("pg_ctl", path=path)
        if initdb and pg_ctl:
            return initdb, pg_ctl
    return None


def server_user(names: tuple[str, ...]) -> dict:
    """``subprocess`` arguments running a server's commands as a user it accepts: PostgreSQL and
    MariaDB refuse to run as root, so under root they run as the first of ``names`` that exists;
    otherwise as this user."""
    if os.geteuid() != 0:
        return {}
    for name in names:
        try:
            entry = pwd.getpwnam(name)
        except KeyError:
            continue
        return {"user": entry.pw_uid, "group": entry.pw_gid, "extra_groups": []}
    pytest.skip(f"the server refuses to run as root, and none of the users {', '.join(names)} exists")


def prepare_server(driver: str, extra: str, binaries, missing: str, users: tuple[str, ...]):
    """Skip unless Optuna, the Python ``driver`` (of the ``extra``) and the server ``binaries`` are
    there (``missing`` names them); the binaries, the ``subprocess`` arguments of the user the server
    runs as, and a new directory for its files that this user owns. Not under pytest's temporary
    directory, which only its owner may enter."""
    pytest.importorskip("optuna")
    pytest.importorskip(driver, reason=f"no {driver} driver: pip install 'sb3_hgrn[{extra}]'")
    if binaries is None:
        pytest.skip(f"no server binaries ({missing})")
    as_user = server_user(users)
    root = Path(tempfile.mkdtemp(prefix=f"sb3_hgrn_{extra}_"))
    if as_user:
        os.chown(root, as_user["user"], as_user["group"])
    return binaries, as_user, root


def free_port() -> int:
    """A port number no TCP server uses now (the server only names its socket file after it)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def run_server_command(command: list[str], as_user: dict, cwd: Path, log: Path | None = None) -> None:
    """Run one of the server's commands; fail the test with its output (and the server log) if it fails."""
    done = subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=120, **as_user)
    if done.returncode:
        server_log = log.read_text() if log is not None and log.exists() else ""
        pytest.fail(f"{' '.join(command)} exited {done.returncode}:\n{done.stdout}{done.stderr}{server_log}")


class PostgresServer:
    """A PostgreSQL server of the tests, reached through the Unix socket in ``socket_dir``."""

    def __init__(self, socket_dir: Path, port: int):
        self.socket_dir = socket_dir
        self.port = port

    def new_database(self, name: str) -> str:
        """Create the empty database ``name``; its SQLAlchemy URL."""
        import psycopg

        with psycopg.connect(
            host=str(self.socket_dir), port=self.port, user="postgres", dbname="postgres", autocommit=True
        ) as db:
            db.execute(f"CREATE DATABASE {name}")
        return f"postgresql+psycopg://postgres@/{name}?host={self.socket_dir}&port={self.port}"


@pytest.fixture(scope="module")
def postgres():
    """A PostgreSQL server started for this module in a directory of its own, stopped after it."""
    missing = "initdb, pg_ctl on PATH or in /usr/lib/postgresql/*/bin"
    binaries = postgres_binaries()
    (initdb, pg_ctl), as_user, root = prepare_server(
        "psycopg", "postgres", binaries, missing, ("postgres", "nobody")
    )
    data, log, port = root / "data", root / "server.log", free_port()
    options = f"-k {root} -p {port} -c listen_addresses='' -c fsync=off"
    try:
        init = [initdb, "-D", str(data), *"-U postgres --auth=trust --no-sync -E UTF8 --locale=C".split()]
        run_server_command(init, as_user, root)
        run_server_command(
            [pg_ctl, "-D", str(data), "-l", str(log), "-o", options, "-w", "start"], as_user, root, log
        )
        yield PostgresServer(root, port)
    finally:
        if (data / "postmaster.pid").exists():
            subprocess.run(
                [pg_ctl, "-D", str(data), "-m", "immediate", "stop"],
                cwd=root,
                capture_output=True,
                timeout=60,
                **as_user,
            )
        shutil.rmtree(root, ignore_errors=True)


def mariadb_binaries() -> tuple[str, str] | None:
    """``mariadb-install-db`` and ``mariadbd`` from ``PATH`` or ``/usr/sbin`` and ``/usr/bin``;
    ``None`` when either is missing."""
    path = os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin", "/usr/bin"])
    install_db, server = shutil.which("mariadb-install-db", path=path), shutil.which("mariadbd", path=path)
    return (install_db, server) if install_db and server else None


class MariaDBServer:
    """A MariaDB server of the tests, reached through the Unix socket ``socket``."""

    def __init__(self, socket_path: Path):
        self.socket = socket_path

    def connect(self):
        import pymysql

        return pymysql.connect(unix_socket=str(self.socket), user="root", autocommit=True)

    def new_database(self, name: str) -> str:
        """Create the empty database ``name``; its SQLAlchemy URL."""
        with self.connect() as db, db.cursor() as cursor:
            cursor.execute(f"CREATE DATABASE {name}")
        return f"mysql+pymysql://root@/{name}?unix_socket={self.socket}"


@pytest.fixture(scope="module")
def mariadb():
    """A MariaDB server started for this module in a directory of its own, stopped after it."""
    missing = "mariadb-install-db, mariadbd on PATH or in /usr/sbin"
    binaries = mariadb_binaries()
    (install_db, server_binary), as_user, root = prepare_server(
        "pymysql", "mysql", binaries, missing, ("mysql", "nobody")
    )
    data, log = root / "data", root / "server.log"
    user = ["--user=" + pwd.getpwuid(as_user["user"]).pw_name] if as_user else []
    server = None
    try:
        init = [install_db, "--no-defaults", f"--datadir={data}", "--auth-root-authentication-method=normal"]
        run_server_command([*init, "--skip-test-db", *user], as_user, root)
        options = [f"--datadir={data}", f"--socket={root / 'server.sock'}", f"--log-error={log}"]
        options += ["--skip-networking", f"--pid-file={root / 'server.pid'}"]
        options += ["--innodb-flush-log-at-trx-commit=0"]
        server = subprocess.Popen([server_binary, "--no-defaults", *options, *user], cwd=root, **as_user)
        database = MariaDBServer(root / "server.sock")
        deadline = time.monotonic() + 60
        while True:  # mariadbd has no "wait until ready" flag: connect until it answers
            try:
                database.connect().close()
                break
            except Exception:
                if server.poll() is not None or time.monotonic() > deadline:
                    pytest.fail(f"mariadbd did not start:\n{log.read_text() if log.exists() else ''}")
                time.sleep(0.2)
        yield database
    finally:
        if server is not None and server.poll() is None:
            server.terminate()
            server.wait(timeout=60)
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture(params=["postgres", "mariadb"])
def database(request):
    """Each test server in turn (PostgreSQL, then MariaDB)."""
    return request.getfixturevalue(request.param)


def start_worker(args: list[str]) -> subprocess.Popen:
    """An ``sb3-hgrn tune`` process with one torch thread."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    return subprocess.Popen(
        [*WORKER, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )


def finish(worker: subprocess.Popen) -> tuple[int, str, str]:
    """Wait for ``worker``; its exit status, standard output and standard error."""
    out, err = worker.communicate(timeout=300)
    return worker.returncode, out, err


def test_two_workers_share_a_study_in_one_database(database, tmp_path):
    import optuna

    database_url = database.new_database("two_workers")
    space = tmp_path / "space.yml"
    space.write_text(SPACE, encoding="utf-8")
    shared = [
        "--search-space",
        str(space),
        "--storage",
        database_url,
        "--study-name",
        STUDY,
        "--n-trials",
        "2",
    ]
    start = time.perf_counter()
    workers = [
        start_worker([*shared, "--sampler-seed", str(seed), "--folder", str(tmp_path / machine)])
        for machine, seed in (("machine_a", 100), ("machine_b", 200))
    ]
    results = [finish(worker) for worker in workers]
    wall = time.perf_counter() - start
    for code, out, err in results:
        assert code == 0, f"a worker exited {code}:\n{out}\n{err}"

    trials = optuna.load_study(storage=database_url, study_name=STUDY).get_trials()
    spans = [(trial.datetime_start, trial.datetime_complete) for trial in trials]
    overlapping = any(a[0] < b[1] and b[0] < a[1] for i, a in enumerate(spans) for b in spans[i + 1 :])
    trained = sum((end - begin).total_seconds() for begin, end in spans)
    print(
        f"\n2 workers, {len(trials)} trials in {type(database).__name__}: {wall:.1f} s wall, "
        f"{trained:.1f} s in trials, "
        f"trials of both workers ran at once: {overlapping}"
    )
    assert [trial.state for trial in trials] == [optuna.trial.TrialState.COMPLETE] * 4
    assert sorted(trial.number for trial in trials) == [0, 1, 2, 3]
    assert len({trial.params["learning_rate"] for trial in trials}) == 4  # the two samplers' seeds differ
    rows = [
        len((tmp_path / machine / STUDY / "trials.csv").read_text().splitlines()) - 1
        for machine in ("machine_a", "machine_b")
    ]
    assert min(rows) >= 2 and max(rows) == 4  # each writes the whole study as it stands when it ends
    assert any(f"study {STUDY!r}: 4 trials (4 complete)" in out for _, out, _ in results)

    other = start_worker(
        [*shared, "--timesteps", "600", "--eval-episodes", "2", "--folder", str(tmp_path / "machine_c")]
    )
    code, _, err = finish(other)
    assert code == 2
    assert (
        f"The study {STUDY!r}" in err and "created for another setup (timesteps, eval_episodes differ)" in err
    )
    assert database_url.split("?")[0] in err
    assert len(optuna.load_study(storage=database_url, study_name=STUDY).get_trials()) == 4


def open_at_once(setup, url: str, barrier, errors) -> None:
    """Open the study ``STUDY`` of ``setup`` at ``url`` once every process has reached ``barrier``;
    put the error's name and message, or ``None``, on the queue ``errors``."""
    import optuna

    from sb3_hgrn.experiments.tune import open_study

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        barrier.wait(timeout=120)
        open_study(setup, url, STUDY)
        errors.put(None)
    except Exception as error:
        errors.put(f"{type(error).__name__}: {error}")


def test_workers_opening_a_new_database_at_once_all_join_one_study(database):
    import optuna

    from sb3_hgrn.experiments.tune import SETUP_ATTR, TuneSetup, load_search_space

    url = database.new_database("at_once")
    setup = TuneSetup("surviving_v0", "soft_hgrn", "ci", 0, load_search_space("soft_hgrn"))
    context = multiprocessing.get_context("spawn")
    barrier, errors = context.Barrier(2), context.Queue()
    workers = [context.Process(target=open_at_once, args=(setup, url, barrier, errors)) for _ in range(2)]
    for worker in workers:
        worker.start()
    outcomes = [errors.get(timeout=180) for _ in workers]
    for worker in workers:
        worker.join(timeout=60)
    assert outcomes == [None] * 2  # each created Optuna's tables, or found another's, and joined
    studies = optuna.get_all_study_summaries(storage=url)
    assert [study.study_name for study in studies] == [STUDY]
    assert studies[0].user_attrs[SETUP_ATTR] == setup.describe()


@pytest.mark.parametrize(
    "driver, url, database, extra",
    [
        ("psycopg", "postgresql+psycopg://postgres@/optuna?host={tmp}", "PostgreSQL", "postgres"),
        ("pymysql", "mysql+pymysql://root@/optuna?unix_socket={tmp}/server.sock", "MySQL", "mysql"),
    ],
)
def test_a_missing_driver_names_the_extra(driver, url, database, extra, tmp_path, capsys, monkeypatch):
    pytest.importorskip("optuna")
    monkeypatch.setitem(sys.modules, driver, None)  # its import fails, as when it is not installed
    url = url.format(tmp=tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        main(["tune", *TOY, "--n-trials", "1", "--storage", url, "--folder", str(tmp_path / "tune")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert f"Cannot open the Optuna storage {url.split('?')[0]}" in err
    assert f"the {database} driver is not installed" in err and f"pip install 'sb3_hgrn[{extra}]'" in err
    assert not (tmp_path / "tune").exists()
