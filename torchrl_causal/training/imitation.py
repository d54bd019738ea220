"""Learning from a privileged teacher: DAgger with the shortest-path oracle, into a Q-network.

A DQN trained from scratch on random layouts learns slowly and generalises
poorly (docs/results.rst: held-out success <= 0.15 after 20k frames). A
privileged teacher that sees the simulator's state -- here
:class:`~torchrl_causal.envs.oracle.ShortestPathPlanner` -- can instead label
every state a sensor-only student visits with the optimal action (DAgger,
Ross, Gordon & Bagnell, AISTATS 2011); the student flies from the camera
and the nine features alone (the privileged-teacher / sensor-only-student
scheme of Loquercio et al., 2021, "Learning high-speed flight in the wild").

:class:`OracleImitation` runs DAgger rounds. In round ``i`` the executed action
is the teacher's with probability ``beta_i`` (``beta_0 = 1``, then
``beta_decay ** i``) and otherwise the student's greedy action; every visited
state is labelled with the teacher's action (replanning only where the drone
left the teacher's plan). All transitions go into one
:class:`~torchrl.data.TensorDictReplayBuffer` (with its buffer transforms, e.g.
a :class:`~torchrl_causal.data.CausalLearningHook`: the CBNs are learned from
the same flights). The Q-network stays a Q-function: its loss is DQfD's
(Hester et al., AAAI 2018): the large-margin term
``max_a [Q(s, a) + margin * (a != a_E)] - Q(s, a_E)`` plus ``td_weight`` times
TorchRL's :class:`~torchrl.objectives.DQNLoss` on the stored transitions, so a
later DQN phase (:class:`~torchrl_causal.training.DQNLoop`) continues from
consistent values.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch

__all__ = ["ImitationConfig", "OracleImitation", "margin_loss"]


def margin_loss(q: torch.Tensor, expert: torch.Tensor, margin: float) -> torch.Tensor:
    """DQfD's large-margin classification loss, averaged over the batch.

    Args:
        q: Q-values ``[B, n_actions]``.
        expert: the teacher's actions ``[B]`` (int64).
        margin: the margin added to every non-expert action.

    Example:
        >>> import torch
        >>> q = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
        >>> margin_loss(q, torch.tensor([0, 0]), 0.5).item()
        0.75
    """
    expert = expert.reshape(-1).long()
    bonus = torch.full_like(q, float(margin))
    bonus.scatter_(-1, expert[:, None], 0.0)
    q_e = q.gather(-1, expert[:, None]).squeeze(-1)
    return ((q + bonus).max(-1).values - q_e).mean()


def _masks(actor) -> bool:
    """Whether a ``QValueActor`` masks its action values with an action mask."""
    return any(getattr(m, "action_mask_key", None) is not None for m in actor.modules())


@dataclass
class ImitationConfig:
    """Options of :class:`OracleImitation`.

    Args:
        rounds: DAgger rounds.
        episodes_per_round: episodes collected per round.
        beta_decay: the teacher acts with probability ``beta_decay ** round``
            (round 0: the teacher only).
        updates_per_frame: gradient steps per collected frame (after each round).
        batch_size: transitions per gradient step.
        lr: Adam learning rate.
        margin: DQfD margin (in reward units).
        td_weight: weight of the TD loss (0: pure imitation).
        target_update_interval: gradient steps between target-network copies.
        max_grad_norm: gradient clipping.
        max_expansions: the teacher's search budget per (re)plan; states it
            cannot solve within it get no label.
        planner_weight: the teacher's heuristic weight (weighted A*): 1.2 plans
            3 % longer than optimal on held-out layouts but 8x faster (worst
            case 1.0 s instead of 11 s, measured from 30 off-start states).
        teacher_actions: the actions the teacher may use (names or indices;
            None: all eight). Leaving out backward / left / right makes every
            horizontal move go where the camera looks, so the teacher's choices
            can be inferred from what the student sees.
        clearance: the teacher's safety margin (m, see
            :class:`~torchrl_causal.envs.oracle.ShortestPathPlanner`).
        seed: seeds the env, the mixture draws and torch.
        progress: a tqdm bar over the rounds.

    Example:
        >>> cfg = ImitationConfig(rounds=4)
        >>> [round(cfg.beta_decay ** r, 3) for r in range(cfg.rounds)]
        [1.0, 0.6, 0.36, 0.216]
    """

    rounds: int = 12
    episodes_per_round: int = 40
    beta_decay: float = 0.6
    updates_per_frame: float = 1.0
    batch_size: int = 32
    lr: float = 3e-4
    margin: float = 0.8
    td_weight: float = 0.0
    target_update_interval: int = 250
    max_grad_norm: float = 10.0
    max_expansions: int = 20_000
    planner_weight: float = 1.2
    teacher_actions: tuple | None = None
    clearance: float = 0.0
    seed: int = 0
    progress: bool = True

    def __post_init__(self):
        for name in ("rounds", "episodes_per_round", "batch_size", "target_update_interval",
                     "max_expansions"):
            val = getattr(self, name)
            if isinstance(val, bool) or not isinstance(val, int) or val < 1:
                raise ValueError(f"ImitationConfig.{name} must be an int >= 1, got {val!r}")
        for name in ("updates_per_frame", "lr", "max_grad_norm"):
            val = getattr(self, name)
            if isinstance(val, bool) or not isinstance(val, (int, float)) or not val > 0:
                raise ValueError(f"ImitationConfig.{name} must be a number > 0, got {val!r}")
        for name in ("margin", "td_weight"):
            val = getattr(self, name)
            if isinstance(val, bool) or not isinstance(val, (int, float)) or val < 0:
                raise ValueError(f"ImitationConfig.{name} must be a number >= 0, got {val!r}")
        if not (isinstance(self.beta_decay, (int, float)) and 0 <= self.beta_decay <= 1):
            raise ValueError(f"ImitationConfig.beta_decay must be in [0, 1], got "
                             f"{self.beta_decay!r}")


class OracleImitation:
    """DAgger from :class:`~torchrl_causal.envs.oracle.ShortestPathPlanner` into a Q-network.

    Args:
        env: an unbatched env over a kinematic
            :class:`~torchrl_causal.envs.DroneNavEnv` (typically random
            training-split layouts), with the feature stack the actor reads.
        actor: the student, a :class:`torchrl.modules.QValueActor` (its
            greedy ``action`` is the student's choice).
        config: an :class:`ImitationConfig`.
        replay_buffer: where every transition (with ``expert_action`` and
            ``expert_valid``) is stored; default: a 50k-frame
            :class:`~torchrl.data.TensorDictReplayBuffer` in RAM.
        loss: the TD loss (default: Double-DQN
            :class:`~torchrl.objectives.DQNLoss` with a Huber loss, gamma 0.95).
        device: where the networks are trained.

    Example:
        >>> import torch
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl.modules import QValueActor
        >>> from torchrl_causal.envs import DroneNavEnv
        >>> from torchrl_causal.modules import ThesisQNet
        >>> env = DroneNavEnv(image_size=36, seed=0)
        >>> actor = QValueActor(ThesisQNet(8, image_size=(36, 36)), in_keys=["pixels"],
        ...                     spec=env.action_spec)
        >>> cfg = ImitationConfig(rounds=1, episodes_per_round=1, progress=False)
        >>> stats = OracleImitation(env, actor, cfg).run()
        >>> stats[0]["frames"], stats[0]["labelled"]
        (12, 12)
    """

    def __init__(self, env, actor, config: ImitationConfig | None = None, *,
                 replay_buffer=None, loss=None, device="cpu"):
        from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

        from ..envs.oracle import OraclePolicy

        self.config = config or ImitationConfig()
        if not isinstance(self.config, ImitationConfig):
            raise ValueError(f"config must be an ImitationConfig, got {config!r}")
        self.env = env
        self.actor = actor
        self.device = torch.device(device)
        self.teacher = OraclePolicy(env, max_expansions=self.config.max_expansions,
                                    weight=self.config.planner_weight,
                                    clearance=self.config.clearance,
                                    actions=self.config.teacher_actions)
        self.buffer = replay_buffer if replay_buffer is not None else TensorDictReplayBuffer(
            storage=LazyTensorStorage(50_000), batch_size=self.config.batch_size)
        if loss is None:
            from .loss import StatefulDQNLoss

            loss = StatefulDQNLoss(actor, loss_function="smooth_l1", delay_value=True,
                                   double_dqn=True, action_space=env.action_spec)
            loss.make_value_estimator(gamma=0.95)
        self.loss = loss
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=self.config.lr)
        self._rng = np.random.default_rng(self.config.seed)
        self.updates = 0
        self.history: list[dict] = []

    # ------------------------------------------------------------ collection
    @torch.no_grad()
    def collect_episode(self, beta: float) -> dict:
        """One episode of the beta-mixture; returns its outcome and counts."""
        env = self.env
        td = env.reset()
        steps, labelled, agree, rows = 0, 0, 0, []
        max_steps = getattr(self.teacher.planner.env, "max_steps", 200)
        reached = crashed = False
        near_goal = False
        for _ in range(max_steps):
            expert = self.teacher.expert_action()
            student = int(self.actor(td.clone().to(self.device))["action"])
            use_teacher = expert is not None and self._rng.random() < beta
            action = expert if use_teacher else student
            td.set("action", torch.tensor(action, dtype=torch.int64))
            td.set("expert_action", torch.tensor(-1 if expert is None else expert))
            td.set("expert_valid", torch.tensor(expert is not None))
            td = env.step(td)
            rows.append(td.exclude("action_value", "chosen_action_value").clone())
            steps += 1
            if expert is not None:
                labelled += 1
                agree += int(student == expert)
            nxt = td["next"]
            if bool(nxt["done"]):
                reached = bool(nxt.get("reached", torch.zeros(1)).any())
                crashed = bool(nxt.get("crashed", torch.zeros(1)).any())
                base = self.teacher.planner.env
                near_goal = base._distance_to_goal_point(base._executor.pose()) < 0.6
                break
            td = env.step_mdp(td)
        self.buffer.extend(torch.stack(rows))
        return {"steps": steps, "labelled": labelled, "agree": agree, "reached": reached,
                "crashed": crashed, "crashed_near_goal": crashed and near_goal}

    # ------------------------------------------------------------ training
    def update(self, n: int) -> float:
        """``n`` gradient steps on the buffer; returns the mean loss."""
        cfg = self.config
        if len(self.buffer) < cfg.batch_size or n <= 0:
            return float("nan")
        total = 0.0
        self.loss.train()
        for _ in range(n):
            batch = self.buffer.sample().to(self.device)
            td_loss = self.loss(batch)["loss"] if cfg.td_weight > 0 else 0.0
            valid = batch["expert_valid"].reshape(-1)
            q = self.actor(batch.clone(False))["action_value"]
            mask = batch.get("action_mask", None)
            if mask is not None and _masks(self.actor):
                # a shielded student cannot take a masked move: no label there
                expert = batch["expert_action"].reshape(-1).clamp(min=0)
                valid = valid & mask.reshape(len(valid), -1).gather(-1, expert[:, None])[:, 0]
            if valid.any():
                m = margin_loss(q[valid], batch["expert_action"].reshape(-1)[valid], cfg.margin)
            else:
                m = torch.zeros((), device=q.device)
            loss = m + cfg.td_weight * td_loss
            self.optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(self.loss.parameters(), cfg.max_grad_norm)
            self.optimizer.step()
            self.updates += 1
            if self.updates % cfg.target_update_interval == 0:
                self._sync_target()
            total += float(loss.detach())
        return total / n

    def _sync_target(self):
        params = getattr(self.loss, "value_network_params", None)
        target = getattr(self.loss, "target_value_network_params", None)
        if params is not None and target is not None:
            target.data.copy_(params.data)

    def run(self, on_round=None) -> list[dict]:
        """All DAgger rounds; returns one dict per round (frames, labelled,
        agreement with the teacher, the round's success and crash rates, beta,
        mean loss, seconds). ``on_round(row)`` is called after each round (e.g.
        to write a CSV row as the run goes)."""
        cfg = self.config
        if not self.history:  # a continued run (more rounds) keeps drawing new layouts
            torch.manual_seed(cfg.seed)
            self.env.set_seed(cfg.seed)
        bar = None
        if cfg.progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=cfg.rounds, desc="DAgger rounds")
        for r in range(len(self.history), cfg.rounds):
            beta = cfg.beta_decay ** r
            t0 = time.perf_counter()
            eps = [self.collect_episode(beta) for _ in range(cfg.episodes_per_round)]
            t1 = time.perf_counter()
            frames = sum(e["steps"] for e in eps)
            loss = self.update(int(math.ceil(frames * cfg.updates_per_frame)))
            labelled = sum(e["labelled"] for e in eps)
            row = {
                "round": r, "beta": beta, "frames": frames, "labelled": labelled,
                "agreement": sum(e["agree"] for e in eps) / max(1, labelled),
                "success_rate": float(np.mean([e["reached"] for e in eps])),
                "crash_rate": float(np.mean([e["crashed"] for e in eps])),
                # crashes within 0.6 m of the goal point (into the board while arriving)
                "crash_near_goal_rate": float(np.mean([e["crashed_near_goal"] for e in eps])),
                "loss": loss, "collect_seconds": t1 - t0,
                "train_seconds": time.perf_counter() - t1,
                "teacher_replans": self.teacher.replans,
            }
            self.history.append(row)
            if on_round is not None:
                on_round(row)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(agree=f"{row['agreement']:.2f}",
                                success=f"{row['success_rate']:.2f}")
        if bar is not None:
            bar.close()
        return list(self.history)

    def state_dict(self) -> dict:
        """Networks, optimiser, counters and round history (for checkpoints)."""
        return {"loss": self.loss.state_dict(), "optim": self.optimizer.state_dict(),
                "updates": self.updates, "history": copy.deepcopy(self.history),
                "rng": self._rng.bit_generator.state, "config": asdict(self.config)}
