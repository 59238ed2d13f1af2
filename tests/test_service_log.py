"""The service says where it serves: the endpoints in force, the --zenoh-config file's
when the options give none (a real ``cfbci serve`` process)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from wire.zenoh_config import free_tcp_endpoint

TIMEOUT = 60.0


def test_the_log_names_the_endpoints_of_the_config_file(tmp_path: Path) -> None:
    endpoint = free_tcp_endpoint()
    config = tmp_path / "service.json5"
    config.write_text(f'{{ listen: {{ endpoints: ["{endpoint}"] }} }}')
    command = [sys.executable, "-m", "cfbci.cli", "serve", "--zenoh-config", str(config)]
    with subprocess.Popen(command, stderr=subprocess.PIPE, text=True) as service:
        try:
            assert service.stderr is not None
            for line in service.stderr:  # ends at the process's end: no hang on a miss
                if "serving on" in line:
                    break
        finally:
            service.terminate()
            service.wait(TIMEOUT)
    assert f"listen=['{endpoint}']" in line, line
