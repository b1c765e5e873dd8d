"""Reading and writing Recal's files (contracts §2-§5), with errors that name the file, the
row and the column (or JSON field) at fault and what was expected.

Output files are written atomically (a temporary file renamed into place), so a failed run
never leaves a partial file behind.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
import stat
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.errors import RecalError
from calibration.identification import Measurements
from calibration.model import KinematicModel, ModelFormatError, model_from_dict, model_to_dict

from .textcheck import document_faults

# The largest magnitude of any number in a JSON document the API takes (a model, a region, a
# body field), checked before its units are known, in the document's own units. A robot cell's lengths are metres (1e3-1e4 in mm), its
# angles a few turns; 1e9 leaves room for any unit and any cell while every product the
# kinematics forms (squares in least squares, 4x4 products) stays far inside float64. Beyond,
# 1e200 overflowed to inf in the solver ("SVD did not converge", a 500 from the API). Tables (CSV
# rows, read with their model's units by the CLI and the API alike) are held to the tighter
# MAX_MAGNITUDE_SI below.
MAX_MAGNITUDE = 1e9


def magnitude_problem(value: float) -> str | None:
    """Why ``value`` cannot be used (NaN, infinite, beyond :data:`MAX_MAGNITUDE`), or None."""
    if not math.isfinite(value):
        return f"expected a finite number, got {value!r}"
    if abs(value) > MAX_MAGNITUDE:
        return f"expected a number from {-MAX_MAGNITUDE:g} to {MAX_MAGNITUDE:g}, got {value!r}"
    return None


# The largest magnitude any number in a Recal file may have, in SI units (metres, radians,
# kilograms): 100 km, or ten thousand turns. Nothing in a robot cell comes near it, and values
# far beyond (1e308) overflow the identification's sums of squares ("SVD did not converge")
# instead of being named.
MAX_MAGNITUDE_SI = 1e5


class InputError(RecalError, ValueError):
    """Bad input, reported as one line: ``file, row R (line L), column 'c': message``.

    ``row`` is the 1-based data row, or ``"header"`` for the header line; ``line`` the line in
    the file (alone when there is no row to name)."""

    def __init__(
        self,
        path: str | os.PathLike,
        message: str,
        *,
        row: int | str | None = None,
        line: int | None = None,
        column: str | None = None,
    ):
        self.path, self.row, self.line, self.column = str(path), row, line, column
        where = [str(path)]
        if row is not None:
            label = "header" if row == "header" else f"row {row}"
            where.append(label + (f" (line {line})" if line is not None else ""))
        elif line is not None:
            where.append(f"line {line}")
        if column is not None:
            where.append(f"column {column!r}")
        super().__init__(": ".join([", ".join(where), message]))


# --------------------------------------------------------------------------- models


def load_model(spec: str | os.PathLike) -> KinematicModel:
    """A model from a ``recal.model/1`` file, or a library robot by name (``ur10e``)."""
    path = Path(spec)
    if not path.exists() and os.sep not in str(spec) and not str(spec).endswith(".json"):
        from calibration import robots

        try:
            return robots.nominal(str(spec))
        except KeyError:
            raise InputError(
                spec, f"no such file, and not a library robot (known: {', '.join(robots.names())})"
            ) from None
    text = read_text(spec, "a recal.model/1 JSON document")
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(
            spec,
            f"line {exc.lineno}, column {exc.colno}: invalid JSON ({exc.msg}); expected a recal.model/1 JSON document",
        ) from None
    faults = document_faults(doc)
    if faults:  # "\ud800" is valid JSON but not text: every verb that wrote it out failed
        loc, message = faults[0]
        where = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc).lstrip(".")
        raise InputError(spec, f"field {where!r}: {message}")
    try:
        return model_from_dict(doc)
    except ModelFormatError as exc:
        raise InputError(
            spec, f"field {exc.field!r}: {str(exc).split(': ', 1)[-1]}" if exc.field else str(exc)
        ) from None


# The largest input file a verb reads (bytes): a million measurement rows are about 100 MB. A
# device or a pipe (`--joints /dev/zero`) is read only this far; a larger regular file is refused
# before it is read. RECAL_MAX_INPUT_BYTES sets another bound (docs/formats.md §6).
DEFAULT_MAX_INPUT_BYTES = 512 * 1024 * 1024


def max_input_bytes() -> int:
    """The input bound in force: ``RECAL_MAX_INPUT_BYTES`` (a positive whole number of bytes, a
    ``k``, ``M`` or ``G`` suffix allowed) or :data:`DEFAULT_MAX_INPUT_BYTES`."""
    raw = os.environ.get("RECAL_MAX_INPUT_BYTES", "").strip()
    if not raw:
        return DEFAULT_MAX_INPUT_BYTES
    scale = {"k": 1024, "m": 1024**2, "g": 1024**3}.get(raw[-1].lower(), 1)
    try:
        value = int(raw[:-1] if scale > 1 else raw) * scale
    except ValueError:
        value = 0
    if value <= 0:
        raise InputError("RECAL_MAX_INPUT_BYTES", f"expected a positive number of bytes (e.g. 512M), got {raw!r}")
    return value


def read_bounded(path: str | os.PathLike) -> bytes:
    """A file's bytes, at most :func:`max_input_bytes` of them: a larger regular file is refused
    from its size before anything is read, and a device or pipe after that many bytes, so the
    memory a verb uses for its input stays bounded (issue 22: ``/dev/zero`` grew to 21.8 GB)."""
    limit = max_input_bytes()
    try:
        with open(path, "rb") as f:
            st = os.fstat(f.fileno())
            if stat.S_ISREG(st.st_mode) and st.st_size > limit:
                raise InputError(
                    path,
                    f"is {st.st_size:,} bytes; expected at most {limit:,} (RECAL_MAX_INPUT_BYTES sets the bound)",
                )
            data = f.read(limit + 1)
    except OSError as exc:
        raise InputError(path, f"cannot read: {exc.strerror or exc}") from None
    if len(data) > limit:
        raise InputError(
            path, f"goes on past {limit:,} bytes; expected at most that (RECAL_MAX_INPUT_BYTES sets the bound)"
        )
    return data


def read_text(path: str | os.PathLike, expected: str, *, encoding: str = "utf-8") -> str:
    """A text file's contents; a file that cannot be read, one over the input bound
    (:func:`read_bounded`), a binary file (NUL bytes) or one that is not UTF-8 raises
    ``InputError`` (one line) naming where and what was expected."""
    return decode_text(path, read_bounded(path), expected, encoding=encoding)


def decode_text(path: str | os.PathLike, data: bytes, expected: str, *, encoding: str = "utf-8") -> str:
    """``data`` (a file's bytes) as text, refused as :func:`read_text` refuses it."""
    nul = data.find(b"\x00")
    if nul >= 0:
        raise InputError(
            path,
            f"is a binary file (a NUL byte at byte {nul + 1}); expected {expected} (UTF-8 text)",
            line=data.count(b"\n", 0, nul) + 1,
        )
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as exc:
        raise InputError(
            path,
            f"byte {exc.start + 1} (0x{data[exc.start]:02x}) is not UTF-8 text; expected "
            f"{expected} in UTF-8 (save it as UTF-8)",
            line=data.count(b"\n", 0, exc.start) + 1,
        ) from None


def check_output(path: str | os.PathLike) -> None:
    """Fail before any work is done when ``path`` cannot be written (its folder is missing or
    not writable, or it is a folder)."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise InputError(path, "cannot write: it is a folder; expected a file name")
    if not folder.is_dir():
        raise InputError(path, f"cannot write: the folder {str(folder)!r} does not exist")
    if not os.access(folder, os.W_OK):
        raise InputError(path, f"cannot write: no permission to write in the folder {str(folder)!r}")


def write_atomic(path: str | os.PathLike, text: str | bytes) -> None:
    """Write ``text`` (or ``bytes``, written as they are) to ``path`` all at once: a temporary
    file in the same folder, renamed."""
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent if str(path.parent) else ".", prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise InputError(path, f"cannot write: {exc.strerror or exc}") from None
    try:
        with os.fdopen(fd, "wb") if isinstance(text, bytes) else os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def save_model(path: str | os.PathLike, model: KinematicModel, extra: dict | None = None) -> None:
    doc = model_to_dict(model)
    if extra:
        doc.update(extra)
    write_atomic(path, json.dumps(doc, indent=2) + "\n")


# --------------------------------------------------------------------------- CSV tables


@dataclass(frozen=True)
class Table:
    """A parsed CSV: header names, the rows as strings, and each row's file line number."""

    path: str
    header: list[str]
    rows: list[list[str]]
    lines: list[int]
    header_line: int = 1

    def has(self, column: str) -> bool:
        return column in self.index

    @property
    def index(self) -> dict[str, int]:
        return {name: i for i, name in enumerate(self.header)}

    @property
    def n_rows(self) -> int:
        return len(self.rows)

    def numbers(
        self, column: str, *, scale: float = 1.0, required: bool = True, allow_empty: bool = False
    ) -> np.ndarray:
        """Column as floats (times ``scale``); a bad cell raises ``InputError`` naming it."""
        if column not in self.index:
            if required:
                raise InputError(
                    self.path,
                    f"missing column; expected a column {column!r} (the header has: {', '.join(self.header)})",
                    row="header",
                    line=self.header_line,
                    column=column,
                )
            return np.full(len(self.rows), np.nan)
        k = self.index[column]
        out = np.empty(len(self.rows))
        for r, (row, line) in enumerate(zip(self.rows, self.lines)):
            cell = row[k].strip() if k < len(row) else ""
            if cell == "" and allow_empty:
                out[r] = np.nan
                continue
            try:
                v = float(cell)
            except ValueError:
                raise InputError(
                    self.path, f"expected a number, got {cell!r}", row=r + 1, line=line, column=column
                ) from None
            if not math.isfinite(v):
                raise InputError(
                    self.path, f"expected a finite number, got {cell!r}", row=r + 1, line=line, column=column
                )
            if abs(v * scale) > MAX_MAGNITUDE_SI:
                raise InputError(
                    self.path,
                    f"{cell} is beyond any robot cell; expected a magnitude of at most "
                    f"{MAX_MAGNITUDE_SI / scale:.6g} in the model's units",
                    row=r + 1,
                    line=line,
                    column=column,
                )
            out[r] = v * scale
        return out

    def strings(self, column: str) -> list[str | None]:
        if column not in self.index:
            return [None] * len(self.rows)
        k = self.index[column]
        return [(row[k].strip() or None) if k < len(row) else None for row in self.rows]


def _check_line_ends(path: str | os.PathLike, text: str) -> None:
    """Refuse a carriage return that ends a line alone in a file of LF or CR LF lines: the rows
    it separates would be read as one (csv refuses it mid-file; a program's reader would not)."""
    cr = text.find("\r")
    while cr >= 0 and text.startswith("\r\n", cr):
        cr = text.find("\r", cr + 2)
    if cr >= 0:
        raise InputError(
            path,
            "a carriage return (CR) alone ends this line; expected every line to end with LF or CR LF "
            "(the file mixes line ends: save it with one kind)",
            line=text.count("\n", 0, cr) + 1,
        )


def _csv_rows(path: str | os.PathLike, text: str):
    """The rows of ``text`` as csv reads them; a row csv cannot read (a field over its limit, a
    stray quote at the end) is one ``InputError`` naming the line."""
    reader = csv.reader(io.StringIO(text))
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            if "field larger than field limit" in str(exc):
                what = (
                    f"has a field longer than {csv.field_size_limit():,} characters; expected numbers and short names"
                )
            else:
                what = f"cannot be read as CSV ({exc}); expected comma-separated values"
            raise InputError(path, what, line=reader.line_num) from None
        yield row


def check_csv_text(path: str | os.PathLike, text: str) -> None:
    """Refuse (``InputError`` naming the line) a CSV text the reader cannot take: what
    :func:`read_table` would refuse before looking at columns. For text kept to be read later (a
    task file registered with a cell): refused when it arrives, not when the night's job reads it."""
    _check_line_ends(path, text)
    for _ in _csv_rows(path, text):
        pass


def read_table(path: str | os.PathLike) -> Table | ColumnTable:
    """Read a CSV with one header line; ``#`` starts a comment line; blank lines are skipped.

    Two readers give the same table: the columnar one (:class:`ColumnTable`, pyarrow) for the
    files it can take as they are, and the Python one (:class:`Table`) for the rest and for every
    error, so that a fault is always named by the same words, row and column.
    ``RECAL_CSV_READER=python`` uses the Python one alone (the benchmark's baseline)."""
    raw = read_bounded(path)
    if os.environ.get("RECAL_CSV_READER", "").strip().lower() != "python":
        fast = ColumnTable.read(path, raw)
        if fast is not None:
            return fast
    text = decode_text(path, raw, "a CSV file", encoding="utf-8-sig")
    del raw  # the rows are read from the text alone: not both in memory through them
    return _python_table(path, text)


def release_columns() -> None:
    """Give back the memory pyarrow's pool (mimalloc) keeps after a :class:`ColumnTable` is
    dropped: it holds it for later reads, which a verb that reads once and then identifies never
    makes (a million rows: 150 MB through the whole fit)."""
    try:
        import pyarrow as pa
    except ImportError:  # pragma: no cover - a dependency
        return
    pa.default_memory_pool().release_unused()


def _python_table(path: str | os.PathLike, text: str) -> Table:
    """The Python reader: every row of ``text`` (the file decoded) through ``csv``."""
    _check_line_ends(path, text)
    header: list[str] | None = None
    header_line = 1
    rows, lines = [], []
    for lineno, row in enumerate(_csv_rows(path, text), start=1):
        if not row or not "".join(row).strip() or row[0].lstrip().startswith("#"):
            continue
        if header is None:
            header, header_line = [h.strip() for h in row], lineno
            dup = {h for h in header if header.count(h) > 1 and h}
            if dup:
                raise InputError(
                    path,
                    "duplicate column in the header; expected each column once",
                    row="header",
                    line=lineno,
                    column=sorted(dup)[0],
                )
            continue
        if len(row) > len(header) and any(c.strip() for c in row[len(header) :]):
            raise InputError(
                path,
                f"has {len(row)} values; expected at most {len(header)}, one per header column",
                row=len(rows) + 1,
                line=lineno,
            )
        rows.append(row)
        lines.append(lineno)
    if header is None:
        raise InputError(path, "is empty: expected a header line and data rows")
    if not rows:
        raise InputError(path, "has a header but no data rows; expected at least one row after the header")
    return Table(str(path), header, rows, lines, header_line)


# The columns the contracts give as numbers (§3-§5: joints, positions, orientations, sigma, payload,
# task frames): the columnar reader types them as float64 as it parses. Any other column is text.
_NUMERIC_COLUMN = re.compile(r"q\d+|[xyz]|q[wxyz]|r[xyz]|sigma|payload_\w+")


class ColumnTable:
    """A CSV read by pyarrow's columnar reader, with the interface of :class:`Table`.

    It takes only files the two readers read alike: no quote character, no comment or blank-only
    line after the header, a line end of LF or CR LF, every row as long as the header. Anything
    else, and every value :meth:`numbers` would refuse (an empty, non-finite or out-of-range
    cell), is handed to the Python reader (:meth:`python`), whose error names the row, line and
    column. ``rows`` and ``lines`` come from the Python reader too (read when first asked for:
    an error message, a task file's report); the file's bytes are kept for that until the table
    is dropped."""

    def __init__(self, path, raw: bytes | None, header: list[str], header_line: int, columns: dict, n: int):
        self.path, self.header, self.header_line = str(path), header, header_line
        self._raw, self._columns, self._n = raw, columns, n
        self._python: Table | None = None

    @classmethod
    def read(cls, path, raw: bytes) -> ColumnTable | None:
        """The table, or None when the file is one for the Python reader."""
        try:
            import pyarrow as pa
            import pyarrow.compute as pc
            import pyarrow.csv as pacsv
        except ImportError:  # pragma: no cover - a dependency; the Python reader still works
            return None
        body = raw[3:] if raw.startswith(b"\xef\xbb\xbf") else raw
        if b'"' in body or b"\x00" in body or body.count(b"\r") != body.count(b"\r\n"):
            return None
        if not body.isascii():
            try:
                body.decode("utf-8")
            except UnicodeDecodeError:
                return None
        found = _header_line(body)
        if found is None:
            return None
        header, header_line, start = found
        if b"#" in body[start:] or not header or "" in header or len(set(header)) < len(header):
            return None
        types = {h: (pa.float64() if _NUMERIC_COLUMN.fullmatch(h) else pa.string()) for h in header}
        try:
            table = pacsv.read_csv(
                pa.BufferReader(pa.py_buffer(body)[start:]),
                # one thread: a verb reads one file and exits, and pyarrow's thread pool torn down
                # at exit while its threads start aborted a process now and then ("terminate
                # called without an active exception", apache/arrow#34314); a million rows take
                # 0.2 s longer
                read_options=pacsv.ReadOptions(column_names=header, use_threads=False),
                parse_options=pacsv.ParseOptions(newlines_in_values=False),
                convert_options=pacsv.ConvertOptions(
                    column_types=types, null_values=[""], strings_can_be_null=True, quoted_strings_can_be_null=True
                ),
            )
        except (pa.ArrowInvalid, pa.ArrowTypeError, pa.ArrowNotImplementedError):
            return None  # a cell that is not a number, a row of another length: the Python reader says which
        n = table.num_rows
        if n == 0:
            return None
        columns = {h: table.column(h) for h in header}
        # a row whose every cell is empty is a blank line to the Python reader ("  ,  ," included)
        blank = np.ones(n, dtype=bool)
        for h, col in columns.items():
            if types[h] == pa.string():
                filled = pc.fill_null(pc.not_equal(pc.utf8_trim_whitespace(col), ""), False)
                blank &= ~filled.to_numpy(zero_copy_only=False)
            else:
                blank &= col.is_null().to_numpy(zero_copy_only=False)
        if blank.any():
            return None
        # the bytes are kept for the Python reader only where they cannot be read again (a pipe)
        return cls(path, None if _regular_file(path) else raw, header, header_line, columns, n)

    # -- the interface of Table

    @property
    def index(self) -> dict[str, int]:
        return {name: i for i, name in enumerate(self.header)}

    def has(self, column: str) -> bool:
        return column in self._columns

    @property
    def n_rows(self) -> int:
        return self._n

    @property
    def rows(self) -> list[list[str]]:
        return self.python().rows

    @property
    def lines(self) -> list[int]:
        return self.python().lines

    def numbers(
        self, column: str, *, scale: float = 1.0, required: bool = True, allow_empty: bool = False
    ) -> np.ndarray:
        """As :meth:`Table.numbers`; a column the Python reader would refuse or treat otherwise
        (text, an empty cell, a value out of range) is read by it, so that it says why."""
        col = self._columns.get(column)
        if col is None and not required:
            return np.full(self._n, np.nan)
        if col is None or str(col.type) != "double":
            return self.python().numbers(column, scale=scale, required=required, allow_empty=allow_empty)
        v = col.to_numpy(zero_copy_only=False)
        empty = np.isnan(v)  # nulls come out as NaN; a written "nan" is refused below as the Python reader does
        if empty.any():
            written_nan = ~col.is_null().to_numpy(zero_copy_only=False) & empty
            if written_nan.any() or not allow_empty:
                return self.python().numbers(column, scale=scale, required=required, allow_empty=allow_empty)
        out = v * scale
        with np.errstate(invalid="ignore"):
            bad = np.isinf(v) | (np.abs(out) > MAX_MAGNITUDE_SI)
        if bad.any():
            return self.python().numbers(column, scale=scale, required=required, allow_empty=allow_empty)
        return out

    def strings(self, column: str) -> list[str | None]:
        """As :meth:`Table.strings`: each cell stripped, None for an empty one."""
        import pyarrow.compute as pc

        col = self._columns.get(column)
        if col is None:
            return [None] * self._n
        if str(col.type) != "string":
            return self.python().strings(column)
        # a target or label column holds a few names many times: strip each name once
        coded = pc.dictionary_encode(col).combine_chunks()
        names = [v.strip() or None for v in coded.dictionary.to_pylist()]
        lookup = np.array([*names, None], dtype=object)
        return lookup[pc.fill_null(coded.indices, len(names)).to_numpy(zero_copy_only=False)].tolist()

    def python(self) -> Table:
        """The same file read by the Python reader (once)."""
        if self._python is None:
            raw = self._raw if self._raw is not None else read_bounded(self.path)
            self._python = _python_table(self.path, decode_text(self.path, raw, "a CSV file", encoding="utf-8-sig"))
        return self._python


def _regular_file(path) -> bool:
    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except OSError:
        return False


def _header_line(body: bytes) -> tuple[list[str], int, int] | None:
    """The header of a CSV's bytes: its names (stripped), its line number, and the offset where
    the rows start; None when there is none (the Python reader says so)."""
    offset, line = 0, 0
    while offset < len(body):
        end = body.find(b"\n", offset)
        end = len(body) if end < 0 else end + 1
        line += 1
        text = body[offset:end].decode("utf-8").strip()
        offset = end
        if not text or text.startswith("#") or not text.replace(",", "").strip():
            continue
        return [h.strip() for h in next(csv.reader([text]))], line, offset
    return None


def _joint_columns(table: Table, model: KinematicModel) -> None:
    """Check that the table's q columns match the model's joints."""
    n = model.n_joints
    qcols = sorted((h for h in table.header if h[:1] == "q" and h[1:].isdigit()), key=lambda h: int(h[1:]))
    extra = [h for h in qcols if int(h[1:]) > n or int(h[1:]) < 1]
    if extra:
        raise InputError(
            table.path,
            f"the model has {n} joints, so expected joint columns q1..q{n} only "
            f"(the data's joint count does not match the model)",
            row="header",
            line=table.header_line,
            column=extra[0],
        )
    for i in range(1, n + 1):
        if f"q{i}" not in table.index:
            raise InputError(
                table.path,
                f"missing joint column 'q{i}': the model has {n} joints, so expected q1..q{n}",
                row="header",
                line=table.header_line,
                column=f"q{i}",
            )


def read_joints(path: str | os.PathLike, model: KinematicModel, table: Table | None = None) -> np.ndarray:
    """Joint readings (N, n) in SI from columns ``q1..qN`` in the model's units."""
    table = table or read_table(path)
    _joint_columns(table, model)
    u = model.units
    q = np.empty((table.n_rows, model.n_joints))
    for i, j in enumerate(model.joints):  # column by column: no list of columns beside the matrix
        q[:, i] = table.numbers(f"q{i + 1}", scale=u.angle_rad if j.revolute else u.length_m)
    check_joint_limits(table, model, q)
    return q


def check_joint_limits(table: Table, model: KinematicModel, q: np.ndarray, *, tolerance: float = 1e-6) -> None:
    """Refuse joint readings beyond the model's limits (a reading no robot can give: a unit slip,
    a wrong column), naming the first such row and column."""
    limits = model.joint_limits
    outside = (q < limits[:, 0] - tolerance) | (q > limits[:, 1] + tolerance)
    if not np.any(outside):
        return
    r, c = (int(v) for v in np.argwhere(outside)[0])
    j = model.joints[c]
    scale = model.units.angle_rad if j.revolute else model.units.length_m
    unit = model.units.angle if j.revolute else model.units.length
    raise InputError(
        table.path,
        f"{q[r, c] / scale:.6g} is outside joint {j.name}'s limits "
        f"[{j.lower / scale:.6g}, {j.upper / scale:.6g}] {unit}; expected a reading "
        f"within the model's lower and upper",
        row=r + 1,
        line=table.lines[r],
        column=f"q{c + 1}",
    )


def read_measurements(path: str | os.PathLike, model: KinematicModel) -> Measurements:
    """A measurement CSV (contracts §3) for ``model``, in SI."""
    table = read_table(path)
    q = read_joints(path, model, table)
    L = model.units.length_m
    p = np.empty((table.n_rows, 3))
    for k, c in enumerate("xyz"):
        p[:, k] = table.numbers(c, scale=L)
    quat = None
    qcols = ["qw", "qx", "qy", "qz"]
    present = [c for c in qcols if table.has(c)]
    if present:
        if len(present) != 4:
            missing = [c for c in qcols if c not in present]
            raise InputError(
                path,
                "missing column; expected all of qw, qx, qy, qz for an orientation",
                row="header",
                line=table.header_line,
                column=missing[0],
            )
        quat = np.stack([table.numbers(c, allow_empty=True) for c in qcols], axis=1)
        partial = np.isnan(quat).any(axis=1) & ~np.isnan(quat).all(axis=1)
        if np.any(partial):
            r = int(np.nonzero(partial)[0][0])
            col = qcols[int(np.nonzero(np.isnan(quat[r]))[0][0])]
            raise InputError(
                path,
                "expected a number (an orientation needs all four of qw, qx, qy, qz)",
                row=r + 1,
                line=table.lines[r],
                column=col,
            )
        norms = np.linalg.norm(quat, axis=1)
        bad = np.isfinite(norms) & (np.abs(norms - 1.0) > 1e-3)
        if np.any(bad):
            r = int(np.nonzero(bad)[0][0])
            raise InputError(
                path,
                f"the quaternion has norm {norms[r]:.6g}; expected a unit quaternion",
                row=r + 1,
                line=table.lines[r],
                column="qw",
            )
    targets = table.strings("target")
    for r, t in enumerate(targets):
        if t is not None and t not in model.targets:
            known = ", ".join(sorted(model.targets)) or "none"
            raise InputError(
                path,
                f"unknown target {t!r}; expected one of the model's targets ({known})",
                row=r + 1,
                line=table.lines[r],
                column="target",
            )
    sigma = table.numbers("sigma", scale=L, required=False, allow_empty=True)
    if np.any(sigma[np.isfinite(sigma)] <= 0):
        r = int(np.nonzero(np.isfinite(sigma) & (sigma <= 0))[0][0])
        raise InputError(
            path, "expected a positive standard uncertainty", row=r + 1, line=table.lines[r], column="sigma"
        )
    pose_id = table.strings("pose_id") if table.has("pose_id") else None
    data = Measurements(
        q=q,
        p_world=p,
        quat=quat,
        target=np.array(targets, dtype=object),
        sigma=sigma,
        pose_id=None if pose_id is None else np.array(pose_id, dtype=object),
        row=np.arange(1, table.n_rows + 1),
        payload=read_payload(table, model),
    )
    del table
    release_columns()
    return data


PAYLOAD_COLUMNS = ("payload_kg", "payload_x", "payload_y", "payload_z")


def read_payload(table: Table, model: KinematicModel) -> np.ndarray | None:
    """Columns ``payload_kg, payload_x, payload_y, payload_z`` (contracts §3: kg, then the centre of
    gravity in the tool frame in the model's length unit) as (N, 4) SI, or None without
    ``payload_kg``. An empty cell is no payload (0 kg) or a centre of gravity at the tool origin."""
    if not table.has("payload_kg"):
        for c in PAYLOAD_COLUMNS[1:]:
            if table.has(c):
                raise InputError(
                    table.path,
                    "a payload's centre of gravity needs its mass; expected a column 'payload_kg'",
                    row="header",
                    line=table.header_line,
                    column=c,
                )
        return None
    L = model.units.length_m
    cols = [
        table.numbers(c, scale=1.0 if c == "payload_kg" else L, required=False, allow_empty=True)
        for c in PAYLOAD_COLUMNS
    ]
    kg = cols[0]
    if np.any(kg[np.isfinite(kg)] < 0):
        r = int(np.nonzero(np.isfinite(kg) & (kg < 0))[0][0])
        raise InputError(
            table.path, "expected a payload mass >= 0 kg", row=r + 1, line=table.lines[r], column="payload_kg"
        )
    return np.nan_to_num(np.stack(cols, axis=1), nan=0.0)


def parse_payload(text: str, model: KinematicModel, flag: str = "--payload") -> tuple[float, float, float, float]:
    """``KG[,X,Y,Z]`` (a payload's mass, and its centre of gravity in the tool frame in the model's
    length unit, default the tool origin) as SI (kg, x, y, z m). Raises ``ValueError`` with a
    one-line message naming ``flag``."""
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) not in (1, 4) or any(magnitude_problem(v) for v in vals) or vals[0] < 0:
        raise ValueError(
            f"{flag}: expected KG or KG,X,Y,Z (mass >= 0 kg, centre of gravity in the tool frame in "
            f"{model.units.length}, each from {-MAX_MAGNITUDE:g} to {MAX_MAGNITUDE:g}), got {text!r}"
        )
    vals += [0.0] * (4 - len(vals))
    L = model.units.length_m
    return (vals[0], vals[1] * L, vals[2] * L, vals[3] * L)


def format_csv(header: list[str], rows) -> str:
    """CSV text with ``header`` and rows of values (floats written with up to 10 significant digits)."""
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(header)
    for row in rows:
        w.writerow([f"{v:.10g}" if isinstance(v, (float, np.floating)) else v for v in row])
    return out.getvalue()


def replace_spans(text: str, edits: list[tuple[int, int, str]]) -> bytes:
    """``text`` with each ``(start, end)`` character span replaced by its new text, every other
    character as it was, encoded back to the bytes it was read from (UTF-8, undecodable bytes
    kept as surrogates): the rewrite every program format shares (URScript's included)."""
    parts, pos = [], 0
    for s, e, t in sorted(edits):
        if s < pos:
            raise ValueError(f"overlapping edits at character {s}")
        parts += [text[pos:s], t]
        pos = e
    parts.append(text[pos:])
    return "".join(parts).encode("utf-8", "surrogateescape")
