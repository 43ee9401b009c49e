"""The six-state MDP of thesis section 6.4 (and its LfGP fix of section 6.5.3): a tabular sanity case.

States s1..s6 loosely mirror stacking: s1 reset, s2 reached, s3 grasped, s4 lifted, s5 hovering over
the second block, s6 dropped. Action a_nm moves deterministically from s_n to s_m; an action is
written as the pair (n, m). The true reward is R(s5, a55) = +1, R(s1, a15) = -5 and 0 otherwise, the
horizon is 5 steps, no discounting. The learner never sees it: a perfect discriminator gives AIRL-style
labels, +1 for the task's expert pairs and -1 for everything else.

Q-values are fitted like the thesis (and its reference script): after each episode, repeated in-order
sweeps of `Q += alpha * (r + Q(s', a') - Q)` over the whole buffer until they stop changing, where the
bootstrap value comes from the next (s', a') stored in the buffer (SARSA-style) and the last step of
an episode (horizon reached) uses the reward alone. Sweeping in place, in buffer order, with
alpha = 0.1 is what produces the published numbers (2.7 rather than the 3.0 of an exact solve).
"""

from __future__ import annotations

from typing import Literal

StateAction = tuple[int, int]
Episode = list[StateAction]

ACTIONS: tuple[StateAction, ...] = (
    (1, 2),
    (1, 5),
    (2, 3),
    (2, 6),
    (3, 4),
    (3, 6),
    (4, 5),
    (4, 6),
    (5, 1),
    (5, 5),
    (6, 1),
    (6, 6),
)
HORIZON = 5
TRUE_REWARD: dict[StateAction, float] = {(5, 5): 1.0, (1, 5): -5.0}

# Expert demonstrations per task: the main task, and the go-right auxiliary task of section 6.5.3.
DEMONSTRATIONS: dict[str, Episode] = {
    "main": [(1, 2), (2, 3), (3, 4), (4, 5), (5, 5)],
    "go-right": [(1, 2), (2, 3), (3, 4)],
}
EXPERT: dict[str, frozenset[StateAction]] = {task: frozenset(d) for task, d in DEMONSTRATIONS.items()}

# The three epsilon-greedy episodes the thesis walks through (section 6.4).
THESIS_EPISODES: tuple[Episode, ...] = (
    [(1, 5), (5, 5), (5, 5), (5, 5), (5, 5)],
    [(1, 2), (2, 6), (6, 1), (1, 5), (5, 5)],
    [(1, 2), (2, 3), (3, 6), (6, 1), (1, 5)],
)


def discriminator_reward(task: str, sa: StateAction) -> float:
    """Perfect-discriminator AIRL label: +1 for the task's expert pairs, -1 otherwise."""
    return 1.0 if sa in EXPERT[task] else -1.0


def true_return(episode: Episode) -> float:
    """Return of an episode under the real (hidden) reward."""
    return sum(TRUE_REWARD.get(sa, 0.0) for sa in episode)


def fit_q(
    episodes: list[Episode],
    task: str,
    q: dict[StateAction, float] | None = None,
    alpha: float = 0.1,
    tol: float = 1e-5,
    max_sweeps: int = 5000,
    bootstrap: Literal["sarsa", "max"] = "sarsa",
) -> dict[StateAction, float]:
    """Sweep the TD update over all buffered transitions until the total change per sweep < `tol`.

    `q` warm-starts the table (the thesis keeps it across episodes). `bootstrap="max"` uses the best
    buffered action in s' instead of the stored one (Q-learning); the thesis numbers need "sarsa".
    """
    q = dict.fromkeys(ACTIONS, 0.0) | (q or {})
    transitions = [
        (sa, episode[t + 1] if t + 1 < len(episode) else None) for episode in episodes for t, sa in enumerate(episode)
    ]
    seen = {sa for sa, _ in transitions}
    for _ in range(max_sweeps):
        before = dict(q)
        for sa, next_sa in transitions:
            target = discriminator_reward(task, sa)
            if next_sa is not None:
                if bootstrap == "sarsa":
                    target += q[next_sa]
                else:
                    target += max(q[a] for a in seen if a[0] == next_sa[0])
            q[sa] += alpha * (target - q[sa])
        if sum(abs(q[a] - before[a]) for a in ACTIONS) < tol:
            break
    return q


def greedy_action(q: dict[StateAction, float], state: int) -> StateAction:
    """The highest-valued action in `state` (ties go to the first in ACTIONS order)."""
    return max((a for a in ACTIONS if a[0] == state), key=lambda a: q[a])


def greedy_rollout(q: dict[StateAction, float], start: int = 1) -> Episode:
    """One horizon-long episode acting greedily on `q`."""
    episode, state = [], start
    for _ in range(HORIZON):
        action = greedy_action(q, state)
        episode.append(action)
        state = action[1]
    return episode


def thesis_q_history(bootstrap: Literal["sarsa", "max"] = "sarsa") -> list[dict[StateAction, float]]:
    """Main-task Q after each of the three thesis episodes (section 6.4), warm-starting as the thesis."""
    history, q = [], None
    for i in range(len(THESIS_EPISODES)):
        q = fit_q(list(THESIS_EPISODES[: i + 1]), "main", q, bootstrap=bootstrap)
        history.append(q)
    return history


def lfgp_fix() -> tuple[Episode, dict[StateAction, float]]:
    """Section 6.5.3: after the three episodes the scheduler runs the go-right intention.

    The go-right intention fits its Q on the shared buffer plus its own expert transitions (intentions
    also learn from their task's expert data, thesis B.2.6), with the go-right labels, so a55 scores -1
    for it. Its greedy episode goes into the shared buffer and the main intention is refitted on the
    buffer alone, as in section 6.4. Returns that episode and the main task's new Q-table.
    """
    buffer = list(THESIS_EPISODES)
    main_q = thesis_q_history()[-1]
    go_right_episode = greedy_rollout(fit_q([*buffer, DEMONSTRATIONS["go-right"]], "go-right"))
    buffer.append(go_right_episode)
    return go_right_episode, fit_q(buffer, "main", main_q)
