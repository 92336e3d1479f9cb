"""Reading `svkernel render` outputs for the tables of tools/*.sh.

    from render_metrics import cell, metrics, table
    for scene, tag, method, m in metrics(folder): ...
    text = table(rows, columns, header)

Standard library only.
"""
import json
import pathlib


def metrics(folder):
    """(scene folder name, pass tag, method name, its metrics) for every
    method with metrics in every FOLDER/<scene>/render.json, in name order."""
    for d in sorted(p for p in pathlib.Path(folder).iterdir() if (p / "render.json").exists()):
        doc = json.loads((d / "render.json").read_text())
        for p in doc["passes"]:
            for m in p["methods"]:
                if m.get("metrics"):
                    yield d.name, p["tag"], m["method"], m["metrics"]


def cell(e):
    """'2.3 % (-0.4 %)': relative RMSE with noise subtracted ('< noise' when
    the noise hides it) and the mean relative bias."""
    v = e["rel_rmse"]
    rmse = "< noise" if not v else f"{100 * v:.1f} %"
    return f"{rmse} ({100 * e['rel_bias']:+.1f} %)"


def table(rows, columns, header=str):
    """A markdown table: one line per scene of `rows` ({scene: {column:
    cell}}), one column per entry of `columns` headed by header(column);
    missing cells are empty."""
    text = "| scene | " + " | ".join(header(c) for c in columns) + " |\n"
    text += "|---" * (len(columns) + 1) + "|\n"
    for scene, cells in rows.items():
        text += f"| {scene} | " + " | ".join(cells.get(c, "") for c in columns) + " |\n"
    return text
