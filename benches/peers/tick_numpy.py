"""Peer baseline: one MCA-PI tick written the straightforward numpy way.

This is the reference point for the Rust tick benchmarks: what a researcher
would write from Algorithm 1 of Kompella, Kazerounian & Schmidhuber (SAB 2014)
without tuning.  Every basis, including the indicator one, is a dense feature
matrix Φ (pairs × features); each tick builds P^πΦ densely, forms
A = Φᵀ(Φ − γP^πΦ) and solves it from scratch (docs/algorithm.md §2, §5).

Run from the repository root (see run.sh); prints one JSON object per setup:
{"setup": ..., "median_us": ..., "ticks": ..., "repeats": ...}.
"""

import os

# Pin BLAS to one thread before numpy is imported: the baseline is single-threaded.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import json  # noqa: E402
import timeit  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ETA = 0.01  # MCA learning rate η (Eqs. 1-2)
XI_INIT_SD = 0.3  # optimistic initialisation of Ξ (§3)
STIMULUS_MEAN = 6.0  # stimulus delivered at a source, on its own dimension (§6)
STIMULUS_SD = 2.0  # its noise, N(0, 2)
TIE_TOL = 1e-10  # greedy ties: within TIE_TOL·(1 + |max Q|) of the max
RIDGE = 1e-6  # ridge added to A only when np.linalg.solve reports it singular
WARMUP_TICKS = 300
REPEATS = 7
SEED = 2014
THREE_ROOM_MAP = Path("data/three_room.txt")


@dataclass
class Setup:
    """A deterministic environment, its basis and discount.

    Valid pairs are numbered state-major, actions in index order.
    `pair_state[p]`, `pair_action[p]`, `pair_next[p]`: state, action and
    (deterministic) next state of pair p; `pair_of[s, a]`: pair index or -1.
    `sources[s]`: stimulus dimension delivered on arriving in s, or -1.
    """

    name: str
    pair_state: np.ndarray
    pair_action: np.ndarray
    pair_next: np.ndarray
    pair_of: np.ndarray
    sources: np.ndarray
    n_stimuli: int
    phi: np.ndarray
    gamma: float

    @property
    def n_states(self) -> int:
        """Number of states."""
        return self.pair_of.shape[0]


def pairs_from_next(next_state: list[list[int | None]]):
    """Valid-pair arrays from a table next_state[s][a] (None: action unavailable)."""
    n_states, n_actions = len(next_state), len(next_state[0])
    pair_of = np.full((n_states, n_actions), -1, dtype=np.int64)
    pair_state, pair_action, pair_next = [], [], []
    for s, row in enumerate(next_state):
        for a, t in enumerate(row):
            if t is not None:
                pair_of[s, a] = len(pair_state)
                pair_state.append(s)
                pair_action.append(a)
                pair_next.append(t)
    return np.array(pair_state), np.array(pair_action), np.array(pair_next), pair_of


def hallway() -> Setup:
    """Experiment 1: 50-state chain, actions left/right/stay, food at 10, rest at 40."""
    n = 50
    next_state = [[s - 1 if s > 0 else None, s + 1 if s < n - 1 else None, s] for s in range(n)]
    pair_state, pair_action, pair_next, pair_of = pairs_from_next(next_state)
    sources = np.full(n, -1)
    sources[10], sources[40] = 0, 1
    return Setup("hallway", pair_state, pair_action, pair_next, pair_of, sources, 2,
                 np.eye(len(pair_state)), 0.95)


def three_room(basis: str, k: int = 30) -> Setup:
    """Experiment 2: the three-room map; basis "indicator" or "pvf" (k proto-value functions).

    Free cells (anything but `#`) are states in row-major order; actions are
    left, right, north, south, stay; sources `a`, `b`, `c` feed dims 0, 1, 2.
    """
    rows = [line for line in THREE_ROOM_MAP.read_text().splitlines() if line.strip()]
    cell_state: dict[tuple[int, int], int] = {}
    marks: dict[str, int] = {}
    for r, line in enumerate(rows):
        for c, ch in enumerate(line):
            if ch != "#":
                if ch != ".":
                    marks[ch] = len(cell_state)
                cell_state[(r, c)] = len(cell_state)
    moves = [(0, -1), (0, 1), (-1, 0), (1, 0), (0, 0)]
    next_state = [[cell_state.get((r + dr, c + dc)) for dr, dc in moves] for (r, c) in cell_state]
    pair_state, pair_action, pair_next, pair_of = pairs_from_next(next_state)
    sources = np.full(len(cell_state), -1)
    for dim, mark in enumerate("abc"):
        sources[marks[mark]] = dim
    if basis == "indicator":
        name, phi = "three_room_indicator", np.eye(len(pair_state))
    else:
        name = f"three_room_pvf{k}"
        phi = pvf_features(pair_state, pair_action, pair_next, len(cell_state), len(moves), k)
    return Setup(name, pair_state, pair_action, pair_next, pair_of, sources, 3, phi, 0.85)


def pvf_features(pair_state, pair_action, pair_next, n_states, n_actions, k) -> np.ndarray:
    """Dense Φ for proto-value functions: φ(s, a) = e_a ⊗ v(s), k·|A| columns.

    v(s) holds the k eigenvectors with the smallest eigenvalues of the
    normalised Laplacian I − D^{-1/2} W D^{-1/2} of the undirected state graph.
    """
    w = np.zeros((n_states, n_states))
    moving = pair_state != pair_next
    w[pair_state[moving], pair_next[moving]] = 1.0
    w = np.maximum(w, w.T)
    d_inv_sqrt = 1.0 / np.sqrt(w.sum(axis=1))
    laplacian = np.eye(n_states) - d_inv_sqrt[:, None] * w * d_inv_sqrt[None, :]
    _, vectors = np.linalg.eigh(laplacian)
    v = vectors[:, :k]
    phi = np.zeros((len(pair_state), k * n_actions))
    for p, (s, a) in enumerate(zip(pair_state, pair_action)):
        phi[p, a * k:(a + 1) * k] = v[s]
    return phi


class Agent:
    """MCA-PI agent state (Ξ, visit counts, D, π, Q) and its tick (Algorithm 1, lines 5-9)."""

    def __init__(self, setup: Setup, rng: np.random.Generator):
        """Initialisation of docs/algorithm.md §3, all from `rng`."""
        self.setup = setup
        self.rng = rng
        n_pairs = len(setup.pair_state)
        self.xi_table = rng.normal(0.0, XI_INIT_SD, size=(n_pairs, setup.n_stimuli))
        self.visits = np.zeros(n_pairs)
        d = np.abs(rng.normal(size=setup.n_stimuli))
        self.drive = d / np.linalg.norm(d)
        # π as the chosen pair per state: a uniformly random valid action.
        actions = [rng.choice(np.flatnonzero(row >= 0)) for row in setup.pair_of]
        self.policy = setup.pair_of[np.arange(setup.n_states), actions]
        self.q = np.zeros(n_pairs)
        self.lstdq_error = 0.0
        self.state = int(rng.integers(setup.n_states))

    def tick(self, pair: int, xi: np.ndarray) -> None:
        """One MCA-PI tick: the agent took `pair` and received stimulus `xi` (Λ = I)."""
        su = self.setup
        # Line 5: Ξ row update with rate 1/n(s, a), so Ξ is the sample mean.
        self.visits[pair] += 1
        self.xi_table[pair] += (xi - self.xi_table[pair]) / self.visits[pair]
        # Lines 6-7 (Eqs. 1-2): anti-Hebbian drive update, then normalise.
        d = (1 - ETA) * self.drive - ETA * (self.drive @ xi) * xi
        self.drive = d / np.linalg.norm(d)
        # Line 8: reward function.
        r = np.abs(self.xi_table @ self.drive)
        # Line 9: one LSTDQ evaluation of π ...
        phi = su.phi
        p_pi_phi = phi[self.policy[su.pair_next]]
        a = phi.T @ (phi - su.gamma * p_pi_phi)
        b = phi.T @ r
        try:
            w = np.linalg.solve(a, b)
        except np.linalg.LinAlgError:
            w = np.linalg.solve(a + RIDGE * np.eye(a.shape[0]), b)
        q = phi @ w
        # ... and one greedy improvement.
        self.policy = self.greedy(q)
        self.lstdq_error = float(np.linalg.norm(self.q - q))
        self.q = q

    def greedy(self, q: np.ndarray) -> np.ndarray:
        """Greedy policy on q; ties keep the previous action, else a uniform pick among the tied."""
        su = self.setup
        q_sa = np.where(su.pair_of >= 0, q[su.pair_of], -np.inf)
        best = q_sa.max(axis=1, keepdims=True)
        tied = q_sa >= best - TIE_TOL * (1 + np.abs(best))
        policy = self.policy.copy()
        states = np.arange(su.n_states)
        for s in np.flatnonzero(~tied[states, su.pair_action[policy]]):
            policy[s] = su.pair_of[s, self.rng.choice(np.flatnonzero(tied[s]))]
        return policy

    def step(self) -> None:
        """Walk one step by the current policy, receive the stimulus on arrival, and tick."""
        su = self.setup
        pair = int(self.policy[self.state])
        self.state = int(su.pair_next[pair])
        xi = np.zeros(su.n_stimuli)
        dim = su.sources[self.state]
        if dim >= 0:
            xi[dim] = STIMULUS_MEAN + self.rng.normal(0.0, STIMULUS_SD)
        self.tick(pair, xi)


def bench(setup: Setup, seed: int) -> dict:
    """Warm the agent up by its own walk, then time `step` (the tick plus a negligible move)."""
    agent = Agent(setup, np.random.default_rng(seed))
    for _ in range(WARMUP_TICKS):
        agent.step()
    timer = timeit.Timer(agent.step)
    number, _ = timer.autorange()
    times = timer.repeat(repeat=REPEATS, number=number)
    return {
        "setup": setup.name,
        "median_us": round(float(np.median(times)) / number * 1e6, 1),
        "ticks": number,
        "repeats": REPEATS,
    }


def main() -> None:
    """Benchmark the three setups and print one JSON line each."""
    for setup in (hallway(), three_room("indicator"), three_room("pvf")):
        print(json.dumps(bench(setup, SEED)), flush=True)


if __name__ == "__main__":
    main()
