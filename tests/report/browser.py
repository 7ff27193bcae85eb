"""
Open an HTML page in headless Chromium and read back, from the page's own DOM, whether every image loaded and
every table has rows: :func:`check_page`. :func:`chromium` finds Debian's ``chromium`` (installing it with apt-get
when missing, as root) or skips the test with the reason.
"""

from __future__ import annotations

import html
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-dev-shm-usage",
)
RESULT_ID = "sb3-collapse-dom-check"
# Run on the load event (after every image decoded or failed): the findings become a <pre> that --dump-dom prints.
CHECK_SCRIPT = f"""
<script>
window.addEventListener("load", () => {{
  const images = Array.from(document.images).map(img => ({{
    alt: (img.alt || "").slice(0, 80), complete: img.complete, width: img.naturalWidth, height: img.naturalHeight}}));
  const tables = Array.from(document.querySelectorAll("table")).map(t => ({{
    caption: t.caption ? t.caption.textContent.slice(0, 80) : "",
    body_rows: t.tBodies.length ? t.tBodies[0].rows.length : 0,
    columns: t.rows.length ? t.rows[0].cells.length : 0,
    right: Math.max(...Array.from(t.querySelectorAll("td")).map(td => td.getBoundingClientRect().right), 0),
    css_class: t.className}}));
  const pre = document.createElement("pre");
  pre.id = "{RESULT_ID}";
  const width = document.documentElement.clientWidth;
  pre.textContent = JSON.stringify({{images, tables, width, title: document.title}});
  document.body.appendChild(pre);
}});
</script>
"""


def chromium() -> str:
    """
    :return: the path of a Chromium binary; installs Debian's ``chromium`` with apt-get when none is found and
        this process is root with apt-get available
    :raises pytest.skip.Exception: when there is none and it cannot be installed (the reason says why)
    """
    for name in CANDIDATES:
        path = shutil.which(name)
        if path:
            return path
    if shutil.which("apt-get") is None:
        pytest.skip(
            "headless Chromium is needed to check the HTML report: no chromium binary, and no apt-get to install it"
        )
    if os.geteuid() != 0:
        pytest.skip(
            "headless Chromium is needed to check the HTML report: install it with `sudo apt-get install chromium`"
        )
    environment = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    install = subprocess.run(
        ["apt-get", "install", "-y", "-qq", "chromium"],
        capture_output=True,
        text=True,
        env=environment,
        timeout=900,
        check=False,
    )
    if install.returncode != 0:  # the package lists may be missing or stale
        subprocess.run(["apt-get", "update", "-qq"], capture_output=True, env=environment, timeout=600, check=False)
        install = subprocess.run(
            ["apt-get", "install", "-y", "-qq", "chromium"],
            capture_output=True,
            text=True,
            env=environment,
            timeout=900,
            check=False,
        )
    path = shutil.which("chromium")
    if install.returncode != 0 or path is None:
        pytest.skip(f"could not install Debian's chromium with apt-get: {install.stderr.strip()[-500:]}")
    return path


def check_page(page: Path, workdir: Path, binary: str | None = None, timeout: float = 120.0) -> dict:
    """
    Load a copy of ``page`` (with :data:`CHECK_SCRIPT` added before ``</body>``) in headless Chromium, without
    network, and return what the script read from the DOM once the page loaded.

    :param page: the HTML file
    :param workdir: a scratch folder (Chromium's profile and the page copy)
    :param binary: the Chromium binary (default: :func:`chromium`)
    :param timeout: seconds before Chromium is stopped
    :return: ``{"images": [{alt, complete, width, height}], "tables": [{caption, body_rows, columns, right,
        css_class}], "width", "title"}`` (``right``: the right edge of a table's rightmost cell, ``width``: the
        page's, in CSS pixels)
    """
    binary = binary or chromium()
    text = page.read_text()
    assert "</body>" in text, f"{page} has no </body>"
    copy = workdir / f"checked_{page.name}"
    copy.write_text(text.replace("</body>", CHECK_SCRIPT + "</body>", 1))
    profile = workdir / "chromium-profile"
    profile.mkdir(exist_ok=True)
    command = [
        binary,
        *FLAGS,
        f"--user-data-dir={profile}",
        "--virtual-time-budget=10000",
        "--dump-dom",
        copy.resolve().as_uri(),
    ]
    completed = subprocess.run(command, capture_output=True, text=True, timeout=timeout, check=False)
    assert completed.returncode == 0, f"chromium failed ({completed.returncode}): {completed.stderr[-2000:]}"
    dom = completed.stdout
    start = dom.find(f'<pre id="{RESULT_ID}">')
    assert start >= 0, f"the check script did not run; chromium printed: {dom[:500]} ... {completed.stderr[-1000:]}"
    body = dom[start + len(f'<pre id="{RESULT_ID}">') : dom.index("</pre>", start)]
    return json.loads(html.unescape(body))
