"""The dashboard's requests: strict yes/no fields, no cross-site POSTs, the token kept off the
command line, machine names that can name their pages."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from ajtwin.apps.detection.streaming import AnomalyEvent
from ajtwin.cli.dashboard import dashboard
from ajtwin.cli.machine import machine
from ajtwin.store.registry import Registry, RegistryError
from ajtwin.web.access import COMMAND_LINE_TOKEN_WARNING, TOKEN_ENV
from ajtwin.web.app import InputError, parse_advise_request, parse_forecast_request
from test_web_data import hand_print

LIMITS = {
    "atomizer_current_mA": [300.0, 440.0],
    "carrier_flow_sccm": [15.0, 35.0],
    "sheath_flow_sccm": [30.0, 80.0],
}
ODD_NAME = "lab 2 #3? 50%"


@pytest.fixture(scope="module")
def web_store(tmp_path_factory):
    path = tmp_path_factory.mktemp("webreq") / "r.sqlite"
    reg = Registry(path)
    for name in ("alpha", ODD_NAME):
        reg.add_machine(name)
        hand_print(reg, name, seq_before=None)
    # a machine whose newest print clogged and whose nozzle nobody has cleaned since
    reg.add_machine("clogged")
    clog = AnomalyEvent(3600.0, 3540.0, "nozzle_clog", "nozzle clog", ["cusum+ P_c+P_s"])
    hand_print(reg, "clogged", seq_before=None, tag="1")
    hand_print(reg, "clogged", seq_before=1, anomalies=[clog], tag="2")
    reg.close()
    return path


@pytest.fixture(scope="module")
def client(web_store):
    from fastapi.testclient import TestClient

    from ajtwin.web.app import create_app

    app = create_app(web_store)
    yield TestClient(app, base_url="http://127.0.0.1", raise_server_exceptions=False)
    app.state.view.close()


# ------------------------------------------------------------------ yes/no fields
@pytest.mark.parametrize("text", ["false", "true", "0", "no", 0, 1, [], {}])
def test_a_yes_no_field_must_be_a_json_boolean(text):
    """``bool("false")`` is True: the text "false" zeroed θ in the forecast it asked to keep."""
    for field in ("nominal_theta", "with_sensor_noise"):
        with pytest.raises(InputError, match="expected true or false .a JSON boolean."):
            parse_forecast_request({field: text}, LIMITS, [375, 23, 50])
    with pytest.raises(InputError, match="nominal θ: expected true or false"):
        parse_advise_request({"target": "40", "nominal_theta": text})
    # real booleans and an absent or null field stay as they were
    *_, options = parse_forecast_request({"nominal_theta": True}, LIMITS, [375, 23, 50])
    assert options == {"nominal_theta": True, "with_sensor_noise": False}
    assert not parse_advise_request({"target": "40", "nominal_theta": None})["nominal_theta"]


def test_a_text_boolean_is_a_422_with_a_sentence_over_http(client):
    r = client.post("/api/machine/alpha/forecast", json={"nominal_theta": "false"})
    assert r.status_code == 422
    assert r.json()["error"] == ("nominal θ: expected true or false (a JSON boolean), got 'false'")


def test_the_pages_advice_refuses_a_machine_with_an_open_fault_as_the_command_does(client):
    """What-if advice on a machine whose newest print clogged would steer the inputs around
    the clog: refused with the fault and what to do, before any work, unless asked anyway."""
    r = client.post("/api/machine/clogged/advise", json={"target": "40"})
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error.startswith("not advising: print #2 raised a fault no maintenance has closed")
    assert "clean the nozzle, then `ajtwin machine maintain clogged --nozzle-cleaned`" in error
    assert "advise with an open fault" in error
    assert parse_advise_request({"target": "40", "anyway": True})["anyway"]
    assert not parse_advise_request({"target": "40"})["anyway"]


def test_the_pages_show_q_m_in_nanolitres_per_second(client):
    names = client.get("/api/fleet").json()["names"]
    i = names["outputs"].index("Q_m")
    assert names["output_units"][i] == "nL/s" and names["output_scale"][i] == 1e6


# ------------------------------------------------------------------ cross-site requests
@pytest.mark.parametrize(
    "headers",
    [
        {"Origin": "http://evil.example"},
        {"Origin": "null"},  # a sandboxed frame or a local file
        {"Origin": "http://127.0.0.1:9999"},  # another server on this computer
        {"Referer": "http://evil.example/page.html"},  # a browser that sends no Origin
        {"Sec-Fetch-Site": "cross-site"},
    ],
)
def test_a_post_from_another_sites_page_is_refused(client, headers):
    """Any page the operator visits could POST to the dashboard (text/plain needs no CORS
    preflight) and start forecasts: refused with 403 and a sentence, before any work."""
    for path in ("/api/machine/alpha/forecast", "/api/machine/alpha/advise"):
        r = client.post(path, content=b'{"target": "40"}', headers=headers)
        assert r.status_code == 403, (path, headers, r.status_code)
        assert "came from a page of another site" in r.json()["error"]


def test_the_dashboards_own_pages_and_scripts_may_post(client):
    own = {"Origin": "http://127.0.0.1", "Referer": "http://127.0.0.1/whatif/alpha"}
    for headers in (own, {}, {"Sec-Fetch-Site": "same-origin", "Origin": "http://127.0.0.1"}):
        r = client.post(
            "/api/machine/alpha/advise", json={"target": "x"}, headers=headers
        )  # a bad target: the request got through to the form's check
        assert r.status_code == 422 and "not a number" in r.json()["error"], headers
    # reading stays open to any origin's GET (a browser does not let it read the answer)
    assert client.get("/api/fleet", headers={"Origin": "http://evil.example"}).status_code == 200


# ------------------------------------------------------------------ the token
def _invoke(args, env=None):
    # fails after the token checks (the virtual print's onset is beyond its length): the
    # command never serves
    tail = ["--virtual-print", "nozzle_clog", "--virtual-minutes", "2"]
    return CliRunner().invoke(dashboard, [*args, *tail], env=env or {})


def test_token_on_the_command_line_is_warned_about_env_and_file_are_not(web_store, tmp_path):
    store = ["--store", str(web_store), "--host", "0.0.0.0"]
    res = _invoke([*store, "--token", "a-long-token"], env={TOKEN_ENV: ""})
    assert COMMAND_LINE_TOKEN_WARNING in res.output and res.exit_code == 2
    res = _invoke(store, env={TOKEN_ENV: "a-long-token"})
    assert "warning" not in res.output and "onset 3 min" in res.output
    secret = tmp_path / "token"
    secret.write_text("a-long-token-from-a-file\n")
    secret.chmod(0o600)
    res = _invoke([*store, "--token-file", str(secret)], env={TOKEN_ENV: ""})
    assert "warning" not in res.output and "onset 3 min" in res.output
    secret.chmod(0o644)
    res = _invoke([*store, "--token-file", str(secret)], env={TOKEN_ENV: ""})
    assert res.exit_code == 2 and "other users may read it (mode 644)" in res.output
    secret.chmod(0o600)
    res = _invoke([*store, "--token-file", str(secret), "--token", "a-long-token"])
    assert res.exit_code == 2 and "not both" in res.output
    empty = tmp_path / "empty"
    empty.write_text("\n")
    empty.chmod(0o600)
    res = _invoke([*store, "--token-file", str(empty)], env={TOKEN_ENV: ""})
    assert res.exit_code == 2 and "holds no token" in res.output
    # beyond the loopback without any: the advice names the environment variable and the file
    res = _invoke(store, env={TOKEN_ENV: ""})
    assert res.exit_code == 2 and f"--token-file FILE or in ${TOKEN_ENV}" in res.output


def test_a_served_dashboards_token_is_not_on_its_command_line(web_store):
    """Every user of the computer reads command lines (ps): the token goes in the environment."""
    from ajtwin.web.server import DashboardProcess

    token = "not-in-ps-0123456789"
    with DashboardProcess(web_store, token=token) as dash:
        cmdline = Path(f"/proc/{dash.proc.pid}/cmdline").read_bytes()
        assert b"dashboard" in cmdline and token.encode() not in cmdline
        assert dash.get("api/fleet", token="wrong-token-000")[0] == 401
        assert dash.get("api/fleet")[0] == 200


# ------------------------------------------------------------------ machine names
@pytest.mark.parametrize("name", ["a/b", "../../etc/passwd", "a\\b", "..", "."])
def test_machine_add_refuses_names_that_cannot_name_a_page(tmp_path, name):
    store = tmp_path / "r.sqlite"
    res = CliRunner().invoke(machine, ["add", name, "--store", str(store)])
    assert res.exit_code == 1
    assert "may not contain '/' or '\\' nor be '.' or '..'" in res.output
    with pytest.raises(RegistryError, match="one part of its pages' addresses"):
        Registry(store).add_machine(name)


def test_machine_import_refuses_such_a_name_too(tmp_path):
    from ajtwin.store.archive import export_machine, import_machine

    src = Registry(tmp_path / "a.sqlite")
    src.add_machine("m1")
    archive = tmp_path / "m1.tar.gz"
    export_machine(src, "m1", archive)
    dst = Registry(tmp_path / "b.sqlite")
    with pytest.raises(RegistryError, match="may not contain '/'"):
        import_machine(dst, archive, as_name="lab/m1")
    assert dst.machines() == []


def test_pages_link_to_machines_by_encoded_names(client):
    """A name with a space, '#', '?' and '%' (allowed) reaches its pages through every link."""
    fleet = client.get("/").text
    links = set(re.findall(r'href="(/(?:machine|whatif)/[^"]*)"', fleet))
    assert "/machine/lab%202%20%233%3F%2050%25" in links
    assert "/whatif/lab%202%20%233%3F%2050%25" in links
    for link in links:
        page = client.get(link)
        assert page.status_code == 200, link
    machine_page = client.get("/machine/lab%202%20%233%3F%2050%25").text
    assert 'href="/whatif/lab%202%20%233%3F%2050%25"' in machine_page
    whatif = client.get("/whatif/lab%202%20%233%3F%2050%25").text
    assert 'href="/machine/lab%202%20%233%3F%2050%25"' in whatif
    assert client.get("/api/machine/lab%202%20%233%3F%2050%25").json()["name"] == ODD_NAME
