"""mkdocs hook: the benchmarks' figures, published as ``results/NAME.png`` without a copy.

The pages show figures that ``benchmarks/`` writes into ``benchmarks/results/``; this hook adds
those files to the site as they are, so a rerun of a benchmark updates the docs too.
"""

from pathlib import Path

from mkdocs.structure.files import File

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"


def on_files(files, config):
    for png in sorted(RESULTS.glob("*.png")):
        f = File(f"results/{png.name}", src_dir=str(RESULTS.parent), dest_dir=config["site_dir"],
                 use_directory_urls=config["use_directory_urls"])
        f.abs_src_path = str(png)
        files.append(f)
    return files
