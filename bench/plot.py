"""Plot a ``mfgnet bench`` JSON report (matplotlib, ``bench`` extra): ``python -m bench.plot R.json OUT.png``."""

from __future__ import annotations

from pathlib import Path


def plot_report(report: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    its = report["iterations"]
    axes[0].plot([int(k) for k in its], [v["p50"] for v in its.values()], "o-")
    axes[0].set(xlabel="iterations", ylabel="in-process p50 (ms)", title="cost per iteration count")
    sizes = report["working_size"]
    axes[1].plot([int(k) for k in sizes], [v["p50"] for v in sizes.values()], "o-")
    axes[1].set(xlabel="working size (points per cloud)", ylabel="p50 (ms)", title="cost per working size")
    if report.get("accuracy"):
        methods = report["accuracy"][0]["methods"]
        names = list(methods)
        ms = [methods[n]["ms_per_pair"] for n in names]
        err = [methods[n]["iso_r_median"] for n in names]
        axes[2].scatter(ms, err)
        for n, x, y in zip(names, ms, err, strict=True):
            axes[2].annotate(n, (x, y), fontsize=8)
        axes[2].set(
            xlabel="ms per pair",
            ylabel="median rotation error (deg)",
            yscale="log",
            title=f"accuracy vs time ({report['accuracy'][0]['setting']}, n={report['accuracy'][0]['count']})",
        )
    fig.suptitle(f"mfgnet bench {report['date']} - {report['model']} (see caveats in BENCHMARKS.md)")
    fig.tight_layout()
    fig.savefig(out, dpi=90)


def main(argv: list[str] | None = None) -> None:
    import argparse

    from bench.latency import bench_report
    from bench.report_io import checked
    from model.cli_inputs import output_file

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path, help="an mfgnet bench --json report")
    parser.add_argument("out", type=Path, help="the figure to write (.png)")
    args = parser.parse_args(argv)
    report = checked(bench_report, args.report, "REPORT")
    checked(output_file, args.out, "OUT")
    plot_report(report, args.out)


if __name__ == "__main__":
    main()
