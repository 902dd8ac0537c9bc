"""Structure from motion with pycolmap: SIFT, sequential or exhaustive matching, incremental mapping.

Loop detection needs a vocabulary tree. Rather than downloading COLMAP's, we build a small one from this video's
own SIFT descriptors (`pycolmap.VisualIndex.build`), which is enough to recognise revisited viewpoints within one
orbit and needs nothing from the network.
"""

from __future__ import annotations

import contextlib
import errno
import itertools
import logging
import os
import pickle
import shutil
import sqlite3
import subprocess
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TypeVar

import numpy as np

from image2sim_common.outdir import require_free_space
from reconstruction import _opencv_sift
from reconstruction._colmap import pycolmap
from reconstruction._frames import image_size
from reconstruction._parallel import run_jobs_reporting, usable_cores
from reconstruction._types import SfmOptions
from reconstruction.errors import InputError, ReconstructionError, RegistrationError

log = logging.getLogger(__name__)

VOCAB_TREE_WORDS = 256
VOCAB_TREE_DESCRIPTORS = 20_000
# Chunks of frames per extraction worker (and of pairs per matching worker): progress every few seconds and a
# prompt Ctrl-C, for a merge of a few more small databases.
EXTRACTION_CHUNKS_PER_WORKER = 4
MATCHING_CHUNKS_PER_WORKER = 4
T = TypeVar("T")


def _quiet_colmap() -> None:
    """COLMAP logs every step at INFO through glog; keep only what would end the process (FATAL).

    Its errors are ours to say: on 8 real photos of a cake the mapper's "E... Failed to create any sparse model"
    came out beside the one line that says what to do, and a user sees one line (issue 60)."""
    logging_mod = getattr(pycolmap, "logging", None)
    if logging_mod is not None and hasattr(logging_mod, "minloglevel"):
        logging_mod.minloglevel = 3  # 0 INFO, 1 WARNING, 2 ERROR, 3 FATAL


def extract_features(
    database_path: Path,
    image_dir: Path,
    image_names: list[str],
    options: SfmOptions,
    progress: Callable[[int], None] | None = None,
) -> None:
    """SIFT features for every image into a new COLMAP database, all images sharing one camera.

    ``options.sift`` "opencv": OpenCV's SIFT (`reconstruction._opencv_sift`). "colmap" (the default): with one
    extraction thread (reproducible) the frames are cut, in order, into a few chunks per worker
    (`EXTRACTION_CHUNKS_PER_WORKER`), run by ``extraction_workers`` threads (0: one per usable core), each chunk by
    pycolmap's single-threaded extraction into a database of its own; the chunks are then merged in frame order
    (`merge_feature_databases`), which gives the database one thread would write, every table row for row and byte
    for byte (the SQLite file's page layout may differ). ``progress(images_done)`` is called as chunks finish, in
    the calling thread; Ctrl-C waits for the running chunks only.
    """
    # COLMAP aborts the process (SIGABRT) when SQLite finds the disk full, leaving its staging behind: refuse first.
    # Each image's features (a 128-byte descriptor and a 24-byte keypoint each) are written twice: the shares' and
    # the merged database.
    require_free_space(
        database_path.parent,
        2 * len(image_names) * options.max_num_features * 152 + 2**20,
        "SIFT feature extraction",
        error=InputError,
    )
    first_octave = sift_first_octave(image_dir, image_names, options)
    if options.sift == "opencv":
        _opencv_sift.extract(database_path, image_dir, image_names, options, first_octave, progress)
        return
    if options.sift != "colmap":
        raise InputError(f"SfmOptions.sift must be 'opencv' or 'colmap', got {options.sift!r}")
    workers = options.extraction_workers if options.extraction_workers > 0 else usable_cores()
    if options.extraction_threads != 1 or len(image_names) < 2:
        _extract_share(database_path, image_dir, image_names, options, first_octave)
        if progress is not None:
            progress(len(image_names))
        return
    workers = min(workers, len(image_names))
    chunks = _contiguous_shares(image_names, min(len(image_names), workers * EXTRACTION_CHUNKS_PER_WORKER))
    parts = _part_paths(database_path, "share", len(chunks))

    def job(part: Path, chunk: Sequence[str]) -> Callable[[Callable[[int], None]], None]:
        def run(tick: Callable[[int], None]) -> None:
            # pycolmap releases the GIL while it extracts
            _extract_share(part, image_dir, list(chunk), options, first_octave)
            tick(len(chunk))

        return run

    try:
        run_jobs_reporting(
            [job(part, chunk) for part, chunk in zip(parts, chunks, strict=True)],
            workers,
            progress or (lambda _done: None),
        )
        try:
            merge_feature_databases(parts, database_path)
        except UnmergeableSharesError as exc:  # e.g. frames of different sizes: one thread decides as before
            log.info("%s; extracting the features on one thread instead", exc)
            database_path.unlink(missing_ok=True)
            _extract_share(database_path, image_dir, image_names, options, first_octave)
    finally:
        for part in parts:
            part.unlink(missing_ok=True)


def _contiguous_shares(items: Sequence[T], workers: int) -> list[Sequence[T]]:
    """``items`` cut, in order, into ``workers`` contiguous shares of near-equal size."""
    bounds = np.linspace(0, len(items), workers + 1).round().astype(int)
    return [items[a:b] for a, b in itertools.pairwise(bounds)]


def _part_paths(database_path: Path, tag: str, count: int) -> list[Path]:
    """Where the per-share databases go, beside ``database_path``: ``database.<tag><i>.db``."""
    return [database_path.with_name(f"{database_path.stem}.{tag}{i}{database_path.suffix}") for i in range(count)]


def sift_first_octave(image_dir: Path, image_names: Sequence[str], options: SfmOptions) -> int:
    """COLMAP's SIFT ``first_octave`` for these frames: -1 (work on the frame doubled) when the smallest frame's
    longest side, capped at ``max_image_size_px``, is below ``upsample_below_px``, else 0 (`SfmOptions`)."""
    if not image_names:
        return -1
    longest_px = min(max(image_size(image_dir / name)) for name in image_names)
    return -1 if min(longest_px, options.max_image_size_px) < options.upsample_below_px else 0


def _extract_share(
    database_path: Path, image_dir: Path, image_names: list[str], options: SfmOptions, first_octave: int
) -> None:
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = options.max_num_features
    extraction.sift.first_octave = first_octave
    extraction.max_image_size = options.max_image_size_px
    extraction.num_threads = options.extraction_threads  # one: reproducible (`SfmOptions.extraction_threads`)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = options.camera_model
    pycolmap.extract_features(
        database_path,
        image_dir,
        image_names=image_names,
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )


class UnmergeableSharesError(ReconstructionError):
    """Feature databases extracted from shares of the frames that cannot be merged into one extraction's."""


@contextlib.contextmanager
def _full_disk_as_oserror(database: Path) -> Iterator[None]:
    """SQLite's "database or disk is full" as the OSError (ENOSPC, naming the file) that the command line turns into
    one line saying what to free."""
    try:
        yield
    except sqlite3.OperationalError as exc:
        if "full" not in str(exc):
            raise
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(database)) from exc


def merge_feature_databases(parts: list[Path], out: Path) -> None:
    """Appends the images, frames and features of ``parts[1:]`` to a copy of ``parts[0]`` at ``out``, ids shifted
    to follow on, as if one extraction had read every share in turn.

    Each part must hold one extraction with a single camera and the default rig; they must agree on that camera
    (the frames of one video do). Matches are not merged (there are none yet).

    Raises:
        UnmergeableSharesError: the parts disagree on the camera or rig, a part read no image, or holds pose priors.
    """
    with _full_disk_as_oserror(out):
        _merge_feature_databases(parts, out)


def _merge_feature_databases(parts: list[Path], out: Path) -> None:
    shutil.copyfile(parts[0], out)
    con = sqlite3.connect(out)
    try:
        for part in parts[1:]:
            con.execute("ATTACH DATABASE ? AS part", (str(part),))
            for table in ("cameras", "rigs", "rig_sensors"):
                if (
                    con.execute(f"SELECT * FROM main.{table}").fetchall()
                    != con.execute(f"SELECT * FROM part.{table}").fetchall()
                ):
                    raise UnmergeableSharesError(f"the feature shares disagree on {table}")
            if con.execute("SELECT COUNT(*) FROM part.pose_priors").fetchone()[0]:
                raise UnmergeableSharesError("a feature share holds pose priors")
            image_shift = con.execute("SELECT MAX(image_id) FROM main.images").fetchone()[0]
            frame_shift = con.execute("SELECT MAX(frame_id) FROM main.frames").fetchone()[0]
            if image_shift is None or frame_shift is None or not con.execute("SELECT 1 FROM part.images").fetchone():
                raise UnmergeableSharesError("a feature share read no image")
            shifted = {
                "images": ("image_id + :i, name, camera_id", "image_id"),
                "frames": ("frame_id + :f, rig_id", "frame_id"),
                # a camera's data id is its image's id
                "frame_data": ("frame_id + :f, data_id + :i, sensor_id, sensor_type", "rowid"),
                "keypoints": ("image_id + :i, rows, cols, data", "image_id"),
                "descriptors": ("image_id + :i, type, rows, cols, data", "image_id"),
            }
            for table, (columns, order) in shifted.items():
                con.execute(
                    f"INSERT INTO main.{table} SELECT {columns} FROM part.{table} ORDER BY {order}",
                    {"i": image_shift, "f": frame_shift},
                )
            con.commit()
            con.execute("DETACH DATABASE part")
    finally:
        con.close()


@contextlib.contextmanager
def _stderr_to_devnull() -> Iterator[None]:
    """The process's stderr (file descriptor 2) goes to /dev/null inside the block.

    For `VisualIndex.build`: its k-means (faiss) prints "WARNING clustering 256 points to 32 centroids: please
    provide at least 1248 training points" straight to the C stderr on every run, before anything else the user
    sees. Resizing the index to avoid it would change the vocabulary, and with it the reconstruction every figure
    was measured on.
    """
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def build_vocab_tree(database_path: Path, out_path: Path, seed: int = 0) -> Path:
    """A small visual-word index from this database's own descriptors, written where COLMAP can load it.

    The index's k-means draws from COLMAP's process-wide random generator, which has no option of its own: it is
    seeded here, or a second reconstruction in the same process (or after other COLMAP calls) builds another index,
    closes other loops and gives another model. It runs on one thread: on two, the k-means's result depends on how
    the threads interleave (three builds of the sample's index, three indexes, on a 2-core AMD EPYC), and two
    threads built it no faster (2.7 s against 2.6 s).
    """
    with pycolmap.Database.open(database_path) as db:
        descriptors = [db.read_descriptors(image.image_id).to_float().data for image in db.read_all_images()]
    stacked = np.concatenate([d for d in descriptors if len(d)]).astype(np.float32)
    # k-means on up to 20k descriptors, about 80 a word: 1.0 s on the tabletop sample's 2 cores where 60k took 2.4 s,
    # the same 66 of 66 frames registered, the cameras as close to the truth (2026-12-07, `benchmarks/speed.py`).
    rng = np.random.default_rng(0)
    if len(stacked) > VOCAB_TREE_DESCRIPTORS:
        stacked = stacked[rng.choice(len(stacked), VOCAB_TREE_DESCRIPTORS, replace=False)]
    index = pycolmap.VisualIndex.create(128, 64)
    build = pycolmap.VisualIndex.BuildOptions()
    build.num_visual_words = int(min(VOCAB_TREE_WORDS, max(64, len(stacked) // 50)))
    build.num_iterations = 20
    build.num_rounds = 1
    build.num_threads = 1
    pycolmap.set_random_seed(seed)
    with _stderr_to_devnull():
        index.build(build, pycolmap.FeatureDescriptorsFloat(pycolmap.FeatureExtractorType.SIFT, stacked))
    index.write(out_path)
    return out_path


def match_features(
    database_path: Path,
    num_images: int,
    *,
    sequential: bool,
    options: SfmOptions,
    work_dir: Path,
    progress: Callable[[int, int], None] | None = None,
) -> None:
    """Sequential matching with loop detection for videos; exhaustive for small unordered image sets.

    With one matching thread (``options.num_threads`` 1, reproducible) the image pairs COLMAP's pairing would match
    are listed first (its own pair generator, loop detection included), shared out in order among
    ``options.matching_workers`` worker processes (0: one per usable core), each matching and verifying its share
    single-threaded in a copy of the database, and the shares' matches and two-view geometries merged back
    (`merge_match_databases`). Every pair's RANSAC starts from the same seed, so that gives the tables one thread
    writes, row for row and byte for byte (`tests/reconstruction/test_reconstruct.py`), in 10 s instead of 14 s on the
    tabletop sample's 2 cores. Processes, not threads: pycolmap's matching run in several threads of one process at once
    came out different now and then (a keypoint match more or less in a pair: 4 tables of 48 wrong with 6 threads
    matching the same pairs side by side; none of 90 for SIFT extraction, which stays in threads). Each process
    matches its share in a few chunks (`MATCHING_CHUNKS_PER_WORKER`), one after the other in its copy, and
    ``progress(pairs_done, pairs)`` is called as chunks finish, in the calling thread; Ctrl-C waits for the running
    chunks only. With more matching threads COLMAP's own threading runs as before (not reproducible).
    """
    # Each worker matches in a copy of the database, and the matches (about as large as the features, measured on
    # the tabletop sample) are merged back: refused before COLMAP can abort on a full disk.
    workers = options.matching_workers if options.matching_workers > 0 else usable_cores()
    require_free_space(
        database_path.parent, (workers + 2) * database_path.stat().st_size + 2**20, "feature matching", error=InputError
    )
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.num_threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = options.seed
    if sequential:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = options.sequential_overlap
        pairing.quadratic_overlap = True
        pairing.num_threads = options.num_threads
        if options.loop_detection and num_images > 2 * options.sequential_overlap:
            pairing.loop_detection = True
            pairing.vocab_tree_path = build_vocab_tree(database_path, work_dir / "vocab_tree.bin", options.seed)
            # Every 5th frame asks the index for 5 look-alikes at least 2 overlaps away: enough to close an orbit's
            # loop, at a tenth of the cost of querying every frame.
            pairing.loop_detection_period = 5
            pairing.loop_detection_num_images = 5
            pairing.loop_detection_min_index_distance = 2 * options.sequential_overlap
    if options.num_threads != 1 or workers <= 1:
        if sequential:
            pycolmap.match_sequential(
                database_path,
                matching_options=matching,
                pairing_options=pairing,
                verification_options=verification,
                device=pycolmap.Device.cpu,
            )
        else:
            pycolmap.match_exhaustive(
                database_path,
                matching_options=matching,
                verification_options=verification,
                device=pycolmap.Device.cpu,
            )
        return
    with pycolmap.Database.open(database_path) as db:
        generator = (
            pycolmap.SequentialPairGenerator(pairing, db)
            if sequential
            else pycolmap.ExhaustivePairGenerator(pycolmap.ExhaustivePairingOptions(), db)
        )
        name_of = {image.image_id: image.name for image in db.read_all_images()}
        pairs = _unique_pairs(generator.all_pairs())
    if not pairs:
        return
    workers = min(workers, len(pairs))
    parts = _part_paths(database_path, "match", workers)
    shares = _contiguous_shares(pairs, workers)
    chunked = [_contiguous_shares(share, min(len(share), MATCHING_CHUNKS_PER_WORKER)) for share in shares]
    lists = [[work_dir / f"pairs{w}_{c}.txt" for c in range(len(chunks))] for w, chunks in enumerate(chunked)]
    report = progress or (lambda _done, _total: None)

    def job(part: Path, listings: list[Path], chunks: list[Sequence[tuple[int, int]]]) -> Callable[..., None]:
        def run(tick: Callable[[int], None]) -> None:
            _match_share_in_process(part, listings, [len(c) for c in chunks], matching, verification, tick)

        return run

    try:
        # Every copy is taken before any worker starts: COLMAP opens its databases in WAL mode, and copies taken while
        # another thread had the database open came out unreadable ("disk I/O error") or different (tried).
        for part, listings, chunks in zip(parts, lists, chunked, strict=True):
            shutil.copyfile(database_path, part)
            for listing, chunk in zip(listings, chunks, strict=True):
                listing.write_text("".join(f"{name_of[i]} {name_of[j]}\n" for i, j in chunk))
        report(0, len(pairs))
        run_jobs_reporting(
            [job(*args) for args in zip(parts, lists, chunked, strict=True)],
            workers,
            lambda done: report(done, len(pairs)),
        )
        merge_match_databases(parts, database_path)
    finally:
        for path in (*parts, *itertools.chain.from_iterable(lists)):
            path.unlink(missing_ok=True)


def _unique_pairs(pairs: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """``pairs`` without repeats, in either order (sequential pairing with loop detection lists some pairs twice, and
    COLMAP matches a pair once), first occurrence kept."""
    seen: set[tuple[int, int]] = set()
    unique = []
    for i, j in pairs:
        key = (min(i, j), max(i, j))
        if key not in seen:
            seen.add(key)
            unique.append((i, j))
    return unique


# Run by `_match_share_in_process` as `python -c`: imports pycolmap alone (0.4 s, against 1.7 s for this package),
# reads the pickled options from stdin (written by the parent, never from a file), matches the listed pairs chunk by
# chunk into the one database, and prints a line as each chunk is done.
_MATCH_SHARE_CHILD = """
import pickle, sys
import pycolmap
matching, verification, database, listings = pickle.loads(sys.stdin.buffer.read())
if hasattr(getattr(pycolmap, "logging", None), "minloglevel"):
    pycolmap.logging.minloglevel = 1
for listing in listings:
    imported = pycolmap.ImportedPairingOptions()
    imported.match_list_path = listing
    pycolmap.match_image_pairs(
        database,
        matching_options=matching,
        pairing_options=imported,
        verification_options=verification,
        device=pycolmap.Device.cpu,
    )
    print(listing, flush=True)
"""


def _match_share_in_process(
    database_path: Path,
    listings: list[Path],
    pairs_per_listing: list[int],
    matching: pycolmap.FeatureMatchingOptions,
    verification: pycolmap.TwoViewGeometryOptions,
    tick: Callable[[int], None],
) -> None:
    """Matches the pairs of each listing, in order, into ``database_path``, in a process of its own; ``tick(pairs)``
    as each listing is done. The process is ended if ``tick`` raises (the run is stopping) or this fails."""
    payload = pickle.dumps((matching, verification, str(database_path), [str(p) for p in listings]))
    errors_path = database_path.with_name(database_path.name + ".stderr")
    try:
        with errors_path.open("w+b") as errors:
            proc = subprocess.Popen(
                [sys.executable, "-c", _MATCH_SHARE_CHILD],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=errors,
                # One OpenMP thread per process (FAISS, OpenBLAS): the processes already fill the cores; the matches
                # are the same on any number.
                env={**os.environ, "OMP_NUM_THREADS": "1"},
            )
            try:
                assert proc.stdin is not None and proc.stdout is not None
                proc.stdin.write(payload)
                proc.stdin.close()
                done = 0
                for count in pairs_per_listing:
                    if not proc.stdout.readline():
                        break  # the process ended early: its exit status says why
                    done += 1
                    tick(count)
                returncode = proc.wait()
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
                if proc.stdout is not None:
                    proc.stdout.close()
            if returncode != 0 or done < len(pairs_per_listing):  # a share left short would be merged silently
                errors.seek(0)
                tail = errors.read().decode(errors="replace").strip().splitlines()[-3:]
                raise ReconstructionError(
                    f"feature matching failed in its worker process (exit status {returncode}, {done} of "
                    f"{len(pairs_per_listing)} chunks done): {' | '.join(tail)}"
                )
    finally:
        errors_path.unlink(missing_ok=True)


def merge_match_databases(parts: list[Path], out: Path) -> None:
    """Appends the matches and two-view geometries of every part to the database at ``out``, part by part, each in
    pair-id order. The parts are copies of ``out`` (before matching) that each matched their own pairs."""
    with _full_disk_as_oserror(out):
        con = sqlite3.connect(out)
        try:
            for part in parts:
                con.execute("ATTACH DATABASE ? AS part", (str(part),))
                for table in ("matches", "two_view_geometries"):
                    con.execute(f"INSERT INTO main.{table} SELECT * FROM part.{table} ORDER BY pair_id")
                con.commit()
                con.execute("DETACH DATABASE part")
        finally:
            con.close()


def map_incremental(
    database_path: Path,
    image_dir: Path,
    out_dir: Path,
    options: SfmOptions,
    on_image: Callable[[], None] | None = None,
) -> pycolmap.Reconstruction:
    """Incremental mapping; returns the model with the most registered images.

    Raises:
        RegistrationError: no model could be initialised from the matches.
    """
    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.num_threads = options.num_threads
    pipeline.random_seed = options.seed
    pipeline.mapper.random_seed = options.seed
    pipeline.triangulation.random_seed = options.seed
    pipeline.extract_colors = True
    # Global bundle adjustments after the model doubles (COLMAP: grows by 10%), each refined (re-triangulated,
    # outliers filtered, adjusted again) at most twice (COLMAP: 5), and each local one once (COLMAP: 2): a
    # 66-frame orbit needs a few, not a dozen; local bundle adjustment keeps each new frame consistent, and a final
    # global one still runs. On the tabletop sample's matches: 4.7 s instead of 8.0 s at a 1.3 ratio and COLMAP's
    # refinements, camera centres 0.71 against 0.73 mm from the truth after a similarity (2026-12-07;
    # `benchmarks/speed.py`). Global mapping (`pycolmap.global_mapping`, GLOMAP) took 10.4 s at 0.89 mm there.
    pipeline.ba_global_frames_ratio = 2.0
    pipeline.ba_global_points_ratio = 2.0
    pipeline.ba_global_max_refinements = 2
    pipeline.ba_local_max_refinements = 1
    # The mapper works in a copy of the database and writes its models beside it.
    require_free_space(
        database_path.parent, 2 * database_path.stat().st_size + 2**22, "incremental mapping", error=InputError
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(
        database_path, image_dir, out_dir, options=pipeline, next_image_callback=on_image or (lambda: None)
    )
    if not models:
        raise RegistrationError(
            "structure from motion could not start a model: too few frames share features. "
            "Film more slowly with more overlap between frames, and a textured scene"
        )
    best = max(models.values(), key=lambda rec: rec.num_reg_images())
    return best
