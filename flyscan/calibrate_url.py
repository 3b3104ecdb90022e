"""``flyscan calibrate --url``: a calibration session recorded by a running service, fitted
there, and its calibration written here.

Without ``--session-id`` the whole session is run: a plan (``POST /calibration/sessions``),
every pose captured, the pass recorded, the fit; the service must be able to take its robot to
the poses itself, which only the simulated cell's can (a real cell's controller drives its
robot through the plan: docs/commissioning.md). With ``--session-id`` a session recorded so is
fitted (if it is not yet) and fetched. The calibration becomes a version of the service's
history, active only with ``--activate``.
"""
from __future__ import annotations

import json
import time

from flyscan.common import ScanError, UsageError

__all__ = ["run_url"]

#: How long the pass and the fit may take, s.
PASS_TIMEOUT_S = 120.0
FIT_TIMEOUT_S = 600.0


def _call(client, method: str, path: str, **kwargs):
    response = client.request(method, path, **kwargs)
    if response.status_code >= 400:
        try:
            detail = response.json().get("detail")
        except ValueError:
            detail = response.text
        raise ScanError(f"{method} {path}: {response.status_code} {detail}")
    return response.json()


def _until(client, session_id: str, done, timeout_s: float) -> dict:
    deadline = time.monotonic() + timeout_s
    while True:
        info = _call(client, "GET", f"/calibration/sessions/{session_id}")
        if done(info):
            return info
        if time.monotonic() > deadline:
            raise ScanError(f"calibration session {session_id} is still {info['state']} after "
                            f"{timeout_s:g} s")
        time.sleep(0.2)


def run_url(args) -> int:
    import httpx

    headers = {"Authorization": f"Bearer {args.token}"} if args.token else {}
    with httpx.Client(base_url=args.url, headers=headers, timeout=60.0) as client:
        try:
            status = _call(client, "GET", "/status")
        except httpx.HTTPError as exc:
            raise UsageError(f"--url {args.url}: no service answers ({exc})") from None
        session_id = args.session_id
        if session_id is None:
            if not status.get("simulated"):
                raise UsageError("this service drives no robot: record the session from the "
                                 "cell controller (docs/commissioning.md), then fit it with "
                                 "flyscan calibrate --url URL --session-id ID")
            plan = {"led_count": args.led_positions, "sphere_count": args.sphere_positions,
                    "seed": args.seed}
            info = _call(client, "POST", "/calibration/sessions", json=plan)
            session_id, steps = info["session_id"], info["steps"]
            print(f"session {session_id}: {steps} poses", flush=True)
            for index in range(steps):
                _call(client, "POST", f"/calibration/sessions/{session_id}/steps/{index}")
                if (index + 1) % 50 == 0 or index + 1 == steps:
                    print(f"  {index + 1} of {steps} poses captured", flush=True)
            _call(client, "POST", f"/calibration/sessions/{session_id}/pass")
            info = _until(client, session_id, lambda i: i["pass_state"] in ("done", "failed"),
                          PASS_TIMEOUT_S)
            if info["pass_state"] != "done":
                raise ScanError(f"calibration session {session_id}: {info['error']}")
            print("  the pass recorded", flush=True)
        info = _call(client, "GET", f"/calibration/sessions/{session_id}")
        if info["state"] != "fitted":
            _call(client, "POST", f"/calibration/sessions/{session_id}/fit")
            info = _until(client, session_id, lambda i: i["state"] in ("fitted", "failed"),
                          FIT_TIMEOUT_S)
            if info["state"] != "fitted":
                raise ScanError(f"calibration failed: {info['error']}")
        version = info["version"]
        detail = _call(client, "GET", f"/calibration/history/{version}")
        figures = info["figures"]
        print(f"version {version}: views {figures['views_heldout_px']:.4f} px held out; light "
              f"plane {figures['plane_rms_um']} um RMS, sphere centres "
              f"{figures['sphere_centre_rms_um']} um; the pass {figures['led_pass_rms_um']} um")
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(detail["calibration"], indent=1))
        args.out.with_suffix(".report.json").write_text(json.dumps(detail["report"], indent=1))
        chart = client.get(f"/calibration/history/{version}/residuals.png")
        if chart.status_code == 200:
            args.out.with_suffix(".residuals.png").write_bytes(chart.content)
        if args.activate:
            _call(client, "POST", f"/calibration/history/{version}/activate")
            print(f"version {version} is the service's calibration now")
        else:
            print(f"not activated: POST /calibration/history/{version}/activate, or --activate")
    print(f"calibration written to {args.out}")
    return 0
