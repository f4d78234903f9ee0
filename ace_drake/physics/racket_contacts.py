"""Measured ball-racket contacts (the format of ../shared/data/sony_racket_contacts.csv) and the
racket contact model (paper eqs (7)-(8), ``contact.racket_impact``) applied to them, identified
on them and judged on them.

A contact row gives, in the world frame of the match data (this project's: origin at the centre of
the playing surface, x towards the human, z up), the ball's position, velocity and spin just
before and after the contact, the racket frame's velocity v_r, angular velocity w_r and
orientation R_WR (quaternion, scalar last), and the offset d of the ball's centre at the contact
from the racket frame's origin. The racket frame's x axis is the blade normal on the ball's side, so the model's
contact frame C (z along that normal) is R_WC = R_WR [y x z -> x y z]: C's x, y, z are R's y, z, x.
The model sees the velocity of the racket's material point at the contact, v_r + w_r x (d - r n),
and the offset's components in C's x-y (the residual network's input).

Split: contacts of one rally are correlated, and so are a game's, so a split holds out whole games
(``game_keys``: a game is its date, its session and its number; game numbers restart between
sessions, which show as the number falling from one row to the next).
"""

from __future__ import annotations

import csv
import dataclasses
import math
import re
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ace_drake.config import InputError
from ace_drake.physics.contact import racket_impact
from ace_drake.physics.params import AeroParams, BallPhysicsParams, RacketParams

VECTOR_COLUMNS = {
    "p": "Global_Ball_Pos_{}",
    "v_pre": "Global_Ball_Vel_Pre_{}",
    "w_pre": "Global_Ball_Spin_Pre_{}",
    "v_post": "Global_Ball_Vel_Post_{}",
    "w_post": "Global_Ball_Spin_Post_{}",
    "v_racket": "Global_Racket_Velocity_{}",
    "w_racket": "Global_Racket_Spin_{}",
}
OFFSET_COLUMNS = ("Global_dx_pre", "Global_dy_pre", "Global_dz_pre")
QUATERNION_COLUMNS = ("Orientation_X", "Orientation_Y", "Orientation_Z", "Orientation_W")
ID_COLUMNS = ("date", "shot_ID", "serve")
CONFIDENCE_COLUMNS = ("spin_conf_pre", "spin_conf_post")
REQUIRED_COLUMNS = (
    *ID_COLUMNS, *(pattern.format(axis) for pattern in VECTOR_COLUMNS.values() for axis in "XYZ"),
    *QUATERNION_COLUMNS, *OFFSET_COLUMNS,
)
BALL_RADIUS = AeroParams().ball_radius  # m: the file's offsets are of the ball's centre
QUATERNION_TOLERANCE = 1e-3  # |q| may differ from 1 by this much (rounding in the file); more is an error
_SHOT_ID = re.compile(r"/game_(\d+)/rally_(\d+)/shot_(\d+)$")


class RacketContactsError(InputError):
    """The contacts file is missing or malformed; the message names the file, row and field."""


@dataclasses.dataclass(frozen=True)
class RacketContacts:
    """N measured contacts as arrays, world frame, SI units: p, v_pre, w_pre, v_post, w_post,
    v_racket, w_racket, offset (N, 3) (m, m/s, rad/s; offset: the ball's centre from the racket
    frame's origin, m), R_WR (N, 3, 3); shot_ids (N,) str, games (N,) the game key
    (``game_keys``), serve (N,) bool, spin_confidence (N, 2) [pre, post] (NaN when the file has
    none), rows (N,) the file's data row numbers (1 = the first row after the header); skipped:
    {reason: count} of the rows left out (``load_racket_contacts``)."""

    p: np.ndarray
    v_pre: np.ndarray
    w_pre: np.ndarray
    v_post: np.ndarray
    w_post: np.ndarray
    v_racket: np.ndarray
    w_racket: np.ndarray
    offset: np.ndarray
    R_WR: np.ndarray
    shot_ids: np.ndarray
    games: np.ndarray
    serve: np.ndarray
    spin_confidence: np.ndarray
    rows: np.ndarray
    skipped: dict = dataclasses.field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.rows)

    def subset(self, mask) -> "RacketContacts":
        """The contacts where ``mask`` (N,) bool, or at the indices ``mask``, with the same skip counts."""
        fields = {f.name: getattr(self, f.name)[mask] for f in dataclasses.fields(self) if f.name != "skipped"}
        return RacketContacts(**fields, skipped=dict(self.skipped))

    @property
    def R_WC(self) -> np.ndarray:
        """The model's contact frames (N, 3, 3): z along the blade normal towards the ball."""
        return contact_frames(self.R_WR)

    @property
    def v_contact_point(self) -> np.ndarray:
        """Velocity of the racket's material point at the contact (N, 3), m/s: v_r + w_r x (d - r n),
        d the file's offset of the ball's centre (d . n = r plus half the blade's thickness on
        every row) and r n the way from the contact point to it, as ``contact.racket_contact``
        takes the blade's surface point."""
        normal = self.R_WR[:, :, 0]
        return self.v_racket + np.cross(self.w_racket, self.offset - BALL_RADIUS * normal)

    @property
    def contact_offsets(self) -> np.ndarray:
        """The contact point in C's x-y (N, 2), m: the residual network's offset input."""
        return np.einsum("nji,nj->ni", self.R_WC, self.offset)[:, :2]


def quaternion_to_rotation(q_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of unit quaternions (N, 4) [x, y, z, w] (scalar last; SciPy's
    Rotation)."""
    return Rotation.from_quat(np.asarray(q_xyzw, dtype=float)).as_matrix()


def contact_frames(R_WR: np.ndarray) -> np.ndarray:
    """The contact frames R_WC (..., 3, 3) of racket frames R_WR whose x axis is the blade normal
    on the ball's side: C's x, y, z are R's y, z, x (right-handed)."""
    return np.asarray(R_WR, dtype=float)[..., [1, 2, 0]]


def game_keys(dates: Sequence[str], games: Sequence[int]) -> np.ndarray:
    """One key per row, "<date>/session_<s>/game_<g>": rows in file order, a session ending where
    the game number falls (numbers restart between sessions) or the date changes."""
    keys, session, previous = [], 0, None
    for date, game in zip(dates, games):
        if previous is not None and (date != previous[0] or game < previous[1]):
            session = 0 if date != previous[0] else session + 1
        keys.append(f"{date}/session_{session}/game_{game}")
        previous = (date, game)
    return np.array(keys, dtype=object)


def load_racket_contacts(path) -> RacketContacts:
    """The contacts of a CSV in the format of sony_racket_contacts.csv (module docstring).

    Rows with an empty or non-finite value in a required field are left out and counted in
    ``skipped`` by reason (``"missing or non-finite <field>"``); a quaternion whose norm differs
    from 1 by more than QUATERNION_TOLERANCE, a malformed shot_ID or serve flag, a file without
    the required columns (of another kind) or without one usable row is a RacketContactsError
    naming the file, and the row and field where there is one."""
    path = Path(path)
    if not path.is_file():
        raise RacketContactsError(f"racket contacts: no such file {path}")
    with path.open(newline="") as handle:
        reader = csv.DictReader(handle)
        header = reader.fieldnames or []
        missing = [name for name in REQUIRED_COLUMNS if name not in header]
        if missing:
            raise RacketContactsError(f"{path}: not a racket-contacts file (format of sony_racket_contacts.csv): "
                                      f"missing column(s) {', '.join(missing[:6])}{' ...' if len(missing) > 6 else ''}")
        numeric = [name for name in REQUIRED_COLUMNS if name not in ID_COLUMNS]
        values, ids, dates, games, serve, confidence, rows, skipped = [], [], [], [], [], [], [], {}
        for number, row in enumerate(reader, start=1):
            parsed = []
            for name in numeric:
                value = _optional_float(row[name])
                if not math.isfinite(value):
                    reason = f"missing or non-finite {name}"
                    skipped[reason] = skipped.get(reason, 0) + 1
                    break
                parsed.append(value)
            else:
                match = _SHOT_ID.search(row["shot_ID"] or "")
                if match is None:
                    raise RacketContactsError(f"{path}: row {number}, field shot_ID: expected /game_<g>/rally_<r>/shot_<s>, got {row['shot_ID']!r}")
                flag = (row["serve"] or "").strip().lower()
                if flag not in ("true", "false"):
                    raise RacketContactsError(f"{path}: row {number}, field serve: expected True or False, got {row['serve']!r}")
                quaternion = np.array(parsed[-7:-3])
                if abs(np.linalg.norm(quaternion) - 1.0) > QUATERNION_TOLERANCE:
                    raise RacketContactsError(f"{path}: row {number}, fields {'/'.join(QUATERNION_COLUMNS)}: not a unit quaternion "
                                              f"(norm {np.linalg.norm(quaternion):.6f})")
                values.append(parsed)
                ids.append(row["shot_ID"])
                dates.append(row["date"])
                games.append(int(match.group(1)))
                serve.append(flag == "true")
                confidence.append([_optional_float(row.get(name)) for name in CONFIDENCE_COLUMNS])
                rows.append(number)
    if not values:
        raise RacketContactsError(f"{path}: no usable contact rows" + (f" (skipped: {skipped})" if skipped else ""))
    table = np.array(values)
    vectors = {key: table[:, 3 * i: 3 * i + 3] for i, key in enumerate(VECTOR_COLUMNS)}
    quaternions = table[:, 21:25]
    quaternions = quaternions / np.linalg.norm(quaternions, axis=1, keepdims=True)
    return RacketContacts(**vectors, offset=table[:, 25:28], R_WR=quaternion_to_rotation(quaternions), shot_ids=np.array(ids, dtype=object),
                          games=game_keys(dates, games), serve=np.array(serve), spin_confidence=np.array(confidence, dtype=float),
                          rows=np.array(rows), skipped=skipped)


def write_racket_contacts(path, contacts: RacketContacts, dates: Sequence[str] | None = None) -> Path:
    """Writes ``contacts`` as a CSV that ``load_racket_contacts`` reads (the world-frame columns
    of sony_racket_contacts.csv's format, quaternions scalar last, spin confidences if any);
    ``dates`` per row (default: each game key's date). For synthetic contacts and subsets of
    measured ones; the games' sessions come back as ``game_keys`` finds them in row order."""
    path = Path(path)
    dates = [str(game).split("/")[0] for game in contacts.games] if dates is None else list(dates)
    quaternions = rotation_to_quaternion(contacts.R_WR)
    header = [*ID_COLUMNS, *(pattern.format(axis) for pattern in VECTOR_COLUMNS.values() for axis in "XYZ"), *QUATERNION_COLUMNS,
              *OFFSET_COLUMNS, *CONFIDENCE_COLUMNS]
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        for i in range(len(contacts)):
            vectors = [value for key in VECTOR_COLUMNS for value in getattr(contacts, key)[i]]
            writer.writerow([dates[i], contacts.shot_ids[i], "True" if contacts.serve[i] else "False", *map(repr, map(float, vectors)),
                             *map(repr, map(float, quaternions[i])), *map(repr, map(float, contacts.offset[i])),
                             *("" if not math.isfinite(value) else repr(float(value)) for value in contacts.spin_confidence[i])])
    return path


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (N, 4) [x, y, z, w] (scalar last) of rotation matrices (N, 3, 3); the
    inverse of ``quaternion_to_rotation`` (SciPy's Rotation)."""
    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()


def _optional_float(text) -> float:
    """``text`` as a float, NaN where it is empty or not a number."""
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


def split_by_game(contacts: RacketContacts, holdout_fraction: float | None = None, holdout_games: Sequence[str] = (),
                  seed: int = 0) -> tuple[np.ndarray, list[str]]:
    """The held-out mask (N,) and its games: the games named (a key of ``game_keys`` or its end,
    e.g. "session_1/game_2"), or a ``holdout_fraction`` of the games drawn with ``seed`` (at least
    one, never all). Whole games only: no game straddles the split."""
    keys = sorted(set(contacts.games.tolist()))
    if holdout_games:
        chosen = []
        for name in holdout_games:
            found = [key for key in keys if key == name or key.endswith("/" + name.strip("/"))]
            if not found:
                raise InputError(f"--holdout-games: no game {name!r}; the games are {', '.join(keys)}")
            chosen += found
        chosen = sorted(set(chosen))
    else:
        fraction = 0.2 if holdout_fraction is None else float(holdout_fraction)
        if not 0.0 < fraction < 1.0:
            raise InputError(f"--holdout-fraction must be in (0, 1), got {fraction}")
        count = min(len(keys) - 1, max(1, round(fraction * len(keys))))
        if count < 1:
            raise InputError(f"the contacts hold {len(keys)} game(s): a split by game needs at least 2")
        chosen = sorted(np.random.default_rng(seed).choice(keys, size=count, replace=False).tolist())
    if len(chosen) == len(keys):
        raise InputError("the held-out games are all the games: nothing would be left to fit on")
    return np.isin(contacts.games, chosen), chosen


def predict_post_contact(contacts: RacketContacts, racket: RacketParams, radius: float, residual: Callable | None = None):
    """The model's (v+, w+) (N, 3) each, world, for the measured pre-contact states and racket
    motions (paper eqs (7)-(8), ``contact.racket_impact``; ``residual`` as there)."""
    return racket_impact(contacts.v_pre, contacts.w_pre, contacts.v_contact_point, contacts.R_WC, racket, radius,
                         contact_offset=contacts.contact_offsets, residual=residual)


def contact_errors(contacts: RacketContacts, v_post: np.ndarray, w_post: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per contact, the prediction's post-contact velocity error |v+ - v+_measured| (N,) m/s and
    spin error |w+ - w+_measured| (N,) rad/s."""
    return np.linalg.norm(v_post - contacts.v_post, axis=1), np.linalg.norm(w_post - contacts.w_post, axis=1)


# The free parameters of each restitution law, with their bounds (k is shared).
LAW_PARAMETERS = {
    "exponential": (("tangential_k", 0.0, 2.0), ("restitution_gamma1", 0.3, 1.5), ("restitution_gamma2", -0.2, 0.05)),
    "linear": (("tangential_k", 0.0, 2.0), ("restitution_a", 0.3, 1.5), ("restitution_b", -0.1, 0.05)),
}
SPIN_WEIGHT = 0.02  # m: a spin error (rad/s) counts as this many m/s in the fit (the ball's radius)


@dataclasses.dataclass(frozen=True)
class RacketFit:
    """A fitted racket model: ``racket`` (its RacketParams), ``law``, ``parameters`` {name: value},
    ``cost`` (the robust least-squares cost at the optimum), ``contacts`` fitted on, ``success``."""

    racket: RacketParams
    law: str
    parameters: dict
    cost: float
    contacts: int
    success: bool


def fit_racket_model(contacts: RacketContacts, law: str, physics: BallPhysicsParams | None = None,
                     loss: str = "soft_l1", f_scale: float = 0.5) -> RacketFit:
    """Identifies k and the restitution ``law``'s two coefficients (paper eqs (7)-(8); the
    ``LAW_PARAMETERS`` of ``law``) on ``contacts`` with SciPy's bounded least squares: residuals
    the post-contact velocity error (m/s) and the spin error weighted by SPIN_WEIGHT (m), per
    component, under the robust ``loss`` with scale ``f_scale`` (m/s). Starts from
    ``physics.racket`` (default: the paper's)."""
    if law not in LAW_PARAMETERS:
        raise ValueError(f"fit_racket_model: law must be one of {', '.join(LAW_PARAMETERS)}, got {law!r}")
    physics = physics or BallPhysicsParams()
    radius = physics.aero.ball_radius
    names, low, high = zip(*LAW_PARAMETERS[law])
    start = dataclasses.replace(physics.racket, restitution_law=law)

    def model(x) -> RacketParams:
        return dataclasses.replace(start, **{name: float(value) for name, value in zip(names, x)})

    def residuals(x) -> np.ndarray:
        v_post, w_post = predict_post_contact(contacts, model(x), radius)
        return np.concatenate([(v_post - contacts.v_post).ravel(), SPIN_WEIGHT * (w_post - contacts.w_post).ravel()])

    x0 = np.clip([getattr(start, name) for name in names], low, high)
    solution = least_squares(residuals, x0, bounds=(low, high), loss=loss, f_scale=f_scale, x_scale="jac")
    fitted = model(solution.x)
    return RacketFit(fitted, law, {name: float(value) for name, value in zip(names, solution.x)}, float(solution.cost), len(contacts),
                     bool(solution.success))
