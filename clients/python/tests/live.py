"""Runs the client against a live server: python3 live.py BASE_URL LIDAR COLMAP_ZIP OUT_DIR.

Driven by tests/python_client.rs, which starts `sylva serve` and checks what this prints: one
JSON object with what happened.
"""

import json
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from sylva_client import Client, NotFound, Unprocessable  # noqa: E402


def main() -> None:
    base, lidar, colmap, out = sys.argv[1:5]
    c = Client(base)
    report = {"info": "version" in c.info()}
    # A resumed upload: created by a first attempt that sent nothing, finished by the second.
    first = c._json("POST", "/v1/uploads", {
        "kind": "colmap", "filename": os.path.basename(colmap),
        "size": os.path.getsize(colmap)})
    parts = []
    colmap_id = c.upload(colmap, "colmap", upload_id=first["id"],
                         on_part=lambda n, total: parts.append((n, total)))
    report["resumed"] = colmap_id == first["id"] and len(parts) == first["parts_total"]
    report["resumed_state"] = c.upload_state(colmap_id)["state"]
    lidar_id = c.upload(lidar, "lidar")
    job = c.submit({"lidar": lidar_id, "colmap": colmap_id}, params={"until": "ingest"},
                   idempotency_key="python-client-test")
    again = c.submit({"lidar": lidar_id, "colmap": colmap_id}, params={"until": "ingest"},
                     idempotency_key="python-client-test")
    report["idempotent"] = again["id"] == job["id"]
    events = []
    done = c.wait(job["id"], on_event=lambda e, d: events.append(e), timeout=120)
    report["state"] = done["state"]
    report["events"] = sorted(set(events))
    dest = c.download(job["id"], "ingest/report.json", os.path.join(out, "report.json"))
    with open(dest, encoding="utf-8") as f:
        report["downloaded_points"] = json.load(f)["lidar"]["points"]
    report["results_stages"] = sorted(c.results(job["id"])["stages"])
    try:
        c.job("no-such-job")
    except NotFound as e:
        report["not_found"] = [e.status, e.type]
    try:
        c.submit({"colmap": colmap_id})
    except Unprocessable as e:
        report["unprocessable"] = [e.status, e.detail]
    print(json.dumps(report))


if __name__ == "__main__":
    main()
