"""Sessions of LSL streams started from the operator page (`cfbci.view.operator`).

``GET /lsl-streams`` lists the LSL streams the view's machine sees within `LIST_SECONDS`
(`list_streams`). ``POST /start`` with ``"source": "lsl"`` takes the operator's choices
(`BRIDGE_FIELDS`: the EEG stream, the onset-marker stream and the options of ``cfbci
lsl-bridge`` that the page offers), checks them as the bridge and the service would
(`check_bridge`) and gives the command line that runs the bridge (`BridgeStart`): the
view runs that very ``cfbci lsl-bridge`` command, so the page can show it as the CLI
equivalent.

pylsl (which loads liblsl) is imported only when a request needs it; liblsl reads
``LSLAPICFG`` from the view's environment, so the view sees the streams that a bridge it
starts would see.
"""

from __future__ import annotations

import json
import shlex
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from cfbci.service.admission import Rejection, check_config
from cfbci.service.limits import ServiceLimits
from wire import protocol

if TYPE_CHECKING:
    import pylsl

#: Seconds the view waits for the streams on the network to answer.
LIST_SECONDS = 1.0
#: Seconds a stream may take to send its full description (channel labels, units).
INFO_SECONDS = 3.0

#: The choices of an LSL start: name -> (type, the CLI's default; None: none). The
#: option of a name is ``--`` and the name with ``-`` for ``_`` (``learner``: ``--set``).
BRIDGE_FIELDS: dict[str, tuple[type, Any]] = {
    "eeg": (str, None), "markers": (str, None), "moves": (str, "cfbci-moves"),
    "onset_marker": (str, "onset"), "frame": (str, "feedback"), "grid": (int, 5),
    "steps": (int, 500), "seed": (int, 0), "tmin": (float, -0.2), "tmax": (float, 1.0),
    "photodiode": (str, None), "photodiode_threshold": (float, None),
    "photodiode_window": (float, 0.1), "learner": (dict, {}),
}

_KINDS = {int: "an integer", float: "a number", str: "a string", dict: "an object"}


def typed_settings(body: dict[str, Any], fields: dict[str, tuple[type, Any]]) -> dict[str, Any]:
    """The settings of a ``POST /start`` body: each of ``fields`` given or its default (one
    whose value and default are None left out), integers taken as numbers.

    Raises
    ------
    ValueError
        Naming a missing session id, an unknown setting, or one of the wrong type.
    """
    unknown = sorted(set(body) - set(fields) - {"session", "source"})
    if unknown:
        raise ValueError(f"unknown setting(s) {', '.join(unknown)}; the settings are "
                         f"session, {', '.join(fields)}")
    if not isinstance(body.get("session"), str) or not body["session"]:
        raise ValueError("give the session an id (a name, or USER/NAME)")
    values: dict[str, Any] = {}
    for name, (kind, default) in fields.items():
        value = body.get(name, default)
        if value is None:
            continue
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or isinstance(value, bool):
            raise ValueError(f"setting {name!r} must be {_KINDS[kind]}; got {value!r}")
        values[name] = value
    return values


def _role(info: pylsl.StreamInfo) -> str:
    """``"markers"`` for a stream of strings, ``"eeg"`` for a numeric one with a rate, else
    ``"other"``."""
    import pylsl

    if info.channel_format() == pylsl.cf_string:
        return "markers"
    return "eeg" if info.nominal_srate() > 0 else "other"


def _resolve_all() -> list[pylsl.StreamInfo]:
    """Every stream that answers within `LIST_SECONDS`.

    Raises
    ------
    ValueError
        If pylsl cannot load liblsl.
    """
    try:
        import pylsl
    except RuntimeError as error:  # pylsl's "LSL binary library file was not found"
        raise ValueError(f"the view cannot use LSL: pylsl cannot load liblsl ({error})") from None
    return list(pylsl.resolve_streams(wait_time=LIST_SECONDS))


def list_streams() -> list[dict[str, Any]]:
    """The LSL streams on the network, by name: ``name``, ``type``, ``channels``, ``rate``
    (Hz; 0: irregular), ``format``, ``host``, ``source_id`` and ``role`` (``"eeg"``,
    ``"markers"`` or ``"other"``, what the bridge could take them as).

    Raises
    ------
    ValueError
        If pylsl cannot load liblsl.
    """
    from pylsl.lib import string2fmt

    formats = {code: name for name, code in string2fmt.items()}
    return sorted(({
        "name": info.name(), "type": info.type(), "channels": info.channel_count(),
        "rate": info.nominal_srate(), "format": formats.get(info.channel_format(), "?"),
        "host": info.hostname(), "source_id": info.source_id(), "role": _role(info),
    } for info in _resolve_all()), key=lambda s: (s["name"], s["host"], s["source_id"]))


@dataclass(frozen=True)
class BridgeStart:
    """A checked LSL start.

    Attributes
    ----------
    session : str
        The session id.
    arguments : list of str
        The command line after ``cfbci`` (``lsl-bridge ...``).
    config : dict
        The config the bridge will send, as checked.
    """

    session: str
    arguments: list[str]
    config: dict[str, Any]

    @property
    def shown(self) -> str:
        """The command line as an operator types it: ``cfbci lsl-bridge ...``."""
        return shlex.join(["cfbci", *self.arguments])

    @property
    def process_arguments(self) -> list[str]:
        """The command the view runs: this Python's ``cfbci`` CLI with `arguments`."""
        return [sys.executable, "-m", "cfbci.cli", *self.arguments]


def _option(name: str, value: Any) -> list[str]:
    """``--name value`` (``--name=value`` for a value that starts with ``-``)."""
    option = f"--{name.replace('_', '-')}"
    text = str(value)
    return [f"{option}={text}"] if text.startswith("-") else [option, text]


def _setting_text(value: Any) -> str:
    """A learner setting's value as ``--set KEY=VALUE`` reads it back (JSON, or the bare
    text of a string that is no JSON)."""
    if isinstance(value, str):
        try:
            json.loads(value)
        except json.JSONDecodeError:
            return value
    return json.dumps(value)


def bridge_arguments(session: str, values: dict[str, Any], endpoints: list[str]) -> list[str]:
    """``lsl-bridge`` and its options for ``values`` (`BRIDGE_FIELDS`, those at the CLI's
    default left out), connected to ``endpoints``."""
    arguments = ["lsl-bridge", *_option("eeg", values["eeg"]),
                 *_option("markers", values["markers"]), *_option("session", session)]
    for name, value in values.items():
        if name in ("eeg", "markers") or value == BRIDGE_FIELDS[name][1]:
            continue
        if name == "learner":
            for key, setting in value.items():
                arguments += _option("set", f"{key}={_setting_text(setting)}")
        else:
            arguments += _option(name, value)
    for endpoint in endpoints:
        arguments += _option("connect", endpoint)
    return arguments


def _the_stream(name: str, what: str, found: list[pylsl.StreamInfo], listed: set[str]) -> Any:
    """The one stream called ``name`` among ``found``, with its full description.

    Raises
    ------
    ValueError
        If there is none (saying whether it was listed before), more than one, or it does
        not send its description within `INFO_SECONDS`.
    """
    import pylsl

    named = [info for info in found if info.name() == name]
    if not named:
        if name in listed:
            raise ValueError(f"the {what} stream {name!r} is gone: it was listed, and no "
                             "longer answers (has its program stopped?)")
        visible = ", ".join(sorted({info.name() for info in found})) or "none"
        raise ValueError(f"no LSL stream named {name!r} (the {what} stream) on the network; "
                         f"the streams found within {LIST_SECONDS:g} s: {visible}")
    if len(named) > 1:
        hosts = ", ".join(info.hostname() for info in named)
        raise ValueError(f"{len(named)} LSL streams are named {name!r} (on {hosts}): the "
                         "bridge would take whichever answers first; rename one")
    inlet = pylsl.StreamInlet(named[0], recover=False)
    try:
        return inlet.info(timeout=INFO_SECONDS)
    except (pylsl.util.TimeoutError, pylsl.util.LostError):
        raise ValueError(f"the {what} stream {name!r} did not send its description within "
                         f"{INFO_SECONDS:g} s (has its program stopped?)") from None
    finally:
        inlet.close_stream()


def check_bridge(body: dict[str, Any], endpoints: list[str], listed: set[str]) -> BridgeStart:
    """Check an LSL start as ``cfbci lsl-bridge`` and the service would.

    Parameters
    ----------
    body : dict
        The request: ``session`` and `BRIDGE_FIELDS`.
    endpoints : list of str
        The Zenoh endpoints the bridge connects to.
    listed : set of str
        The stream names the page was shown (a stream gone since is named as such).

    Raises
    ------
    ValueError, ProtocolError
        Saying what is wrong: a setting, a stream (missing, gone, named twice, not EEG,
        not strings, without the photodiode channel), a move stream's name taken already,
        a session id or config the service would refuse.
    """
    from acquisition.lsl_bridge import BridgeSettings
    from acquisition.lsl_streams import eeg_stream_meta, marker_stream_shift
    from acquisition.photodiode import PhotodiodeRule

    values = typed_settings(body, BRIDGE_FIELDS)
    sid = body["session"]
    protocol.key(sid, "config")  # ProtocolError on a bad id
    for name, what in (("eeg", "EEG"), ("markers", "onset-marker")):
        if not values.get(name):
            raise ValueError(f"choose the {what} stream")
    rule = "photodiode" in values and PhotodiodeRule(
        values["photodiode"], values.get("photodiode_threshold"), values["photodiode_window"])
    settings = BridgeSettings(
        sid, values["eeg"], values["markers"], values["moves"], seed=values["seed"],
        steps=values["steps"], grid=values["grid"], frame=values["frame"],
        learner=values["learner"], tmin=values["tmin"], tmax=values["tmax"],
        onset_marker=values["onset_marker"], photodiode=rule or None,
    )
    found = _resolve_all()
    if any(info.name() == settings.moves for info in found):
        raise ValueError(f"an LSL stream named {settings.moves!r} is on the network already "
                         "(another bridge's move stream?): the stimulus program could read "
                         "that one; choose another move stream name")
    meta = eeg_stream_meta(_the_stream(settings.eeg, "EEG", found, listed))
    marker_stream_shift(_the_stream(settings.markers, "onset-marker", found, listed))
    config = settings.config(meta)  # what the bridge sends, checked as the service does
    check_config(config, ServiceLimits(), lambda problem: Rejection(problem, sid, 0, 0))
    protocol.encode(protocol.Message("config", sid, 0, 0, config))
    return BridgeStart(sid, bridge_arguments(sid, values, endpoints), config)
