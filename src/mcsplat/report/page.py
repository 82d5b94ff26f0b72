"""The report as one self-contained HTML page: the PNGs are embedded as data URIs, so it opens offline and can be
mailed as one file."""

from __future__ import annotations

import base64
import html

from .runs import RunRecord

STYLE = """body{font-family:system-ui,sans-serif;margin:2em auto;max-width:1100px;color:#222}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:4px 10px;text-align:right}
th{background:#f3f3f3}td:first-child{text-align:left}img{max-width:100%;display:block;margin:0.5em 0 1.5em}
figcaption{color:#555;font-size:0.9em}"""

SUMMARY_COLUMNS = [("psnr", "PSNR (dB)", "{:.2f}"), ("ssim", "SSIM", "{:.4f}"), ("lpips", "LPIPS", "{:.4f}"),
                   ("num_gaussians", "Gaussians", "{:,}"), ("exported_gaussians", "exported", "{:,}"),
                   ("steps", "steps", "{:,}"), ("train_seconds", "train s", "{:.0f}"), ("device", "device", "{}")]


def data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _summary(runs: list[RunRecord]) -> str:
    head = "".join(f"<th>{html.escape(title)}</th>" for _, title, _ in SUMMARY_COLUMNS)
    rows = []
    for run in runs:
        cells = [f"<td>{html.escape(run.name)} ({html.escape(str(run.config.get('strategy', '')))})</td>"]
        for key, _, fmt in SUMMARY_COLUMNS:
            value = run.metrics.get(key)
            cells.append(f"<td>{html.escape(fmt.format(value)) if value is not None else 'n/a'}</td>")
        cells.append(f"<td>{run.dead_fraction:.1%}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><tr><th>run</th>{head}<th>dead</th></tr>{''.join(rows)}</table>"


def _budget_plan(run: RunRecord) -> str:
    """--budget: how the plan went, a row per re-plan (at most a dozen, evenly spread)."""
    plan = run.config.get("budget_plan")
    if not plan:
        return ""
    history = plan.get("history", [])
    every = max(1, -(-len(history) // 12))
    shown = sorted(set(range(0, len(history), every)) | {len(history) - 1}) if history else []
    rows = "".join(f"<tr><td>{h['at_seconds']:.0f} s</td><td>{h['step']:,}</td><td>{h['steps']:,}</td>"
                   f"<td>{h['cap']:,}</td><td>{h['gaussians']:,}</td><td>{h['step_ms']:.1f}</td></tr>"
                   for h in (history[i] for i in shown))
    start = plan.get("resolution_first", plan.get("resolution_start", 1.0))  # the first step's size
    full_at = plan.get("resolution_full_at", 1.0)
    return (f"<p><b>{html.escape(run.name)}</b>: a {plan['budget_seconds']:.0f} s budget planned as it ran: "
            f"{plan['steps']:,} steps, cap {plan['cap']:,}, coarse to fine from {start:g} of the image size to full "
            f"size at {full_at:.0%} of the steps.</p>"
            "<table><tr><th>at</th><th>step</th><th>planned steps</th><th>cap</th><th>Gaussians</th>"
            f"<th>predicted full-size step ms</th></tr>{rows}</table>")


def render_page(title: str, runs: list[RunRecord], figures: list[tuple[str, str, bytes]]) -> str:
    """figures: (file name, caption, PNG bytes) in page order."""
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
             f"<style>{STYLE}</style></head><body><h1>{html.escape(title)}</h1>", _summary(runs)]
    for run in runs:
        data = html.escape(str(run.config.get("data", "")))
        strategy = run.config.get("strategy", "mcmc")  # the cap of the run's strategy, as its plan has it
        cap = run.config.get(strategy, {}).get("cap_max", "n/a")
        parts.append(f"<p><b>{html.escape(run.name)}</b>: {data}, cap {html.escape(str(cap))}, "
                     f"{html.escape(str(run.path))}</p>")
        parts.append(_budget_plan(run))
    for name, caption, png in figures:
        parts.append(f"<figure><figcaption>{html.escape(caption)}</figcaption>"
                     f"<img alt='{html.escape(name)}' src='{data_uri(png)}'></figure>")
    parts.append("</body></html>\n")
    return "\n".join(parts)
