import json
import logging
import math

import pytest
import torch

from avatar_motor.body.motion_state import STATE_DIM
from avatar_motor.model.adaptor import AdaptedDenoiser, AdaptorConfig, load_adaptor, rescale_target, save_adaptor
from avatar_motor.model.denoiser import Denoiser, DenoiserConfig

CFG = DenoiserConfig(width=32, depth=2, heads=4, ff=64, dropout=0.0)


def inputs(B=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randint(0, 50, (B,), generator=g), torch.randn(B, 15, STATE_DIM, generator=g), torch.randn(B, STATE_DIM, generator=g))


def base_net():
    torch.manual_seed(0)
    return Denoiser(CFG).eval()


@pytest.mark.parametrize("kind", ["controlnet", "omni"])
def test_zero_initialised_adaptor_leaves_base_unchanged(kind):
    base = base_net()
    t, x, x0 = inputs()
    ref = base(t, x, x0)
    m = AdaptedDenoiser(base, AdaptorConfig(kind=kind, labels=["a", "b"])).eval()
    assert torch.equal(m(t, x, x0, torch.tensor([0, 1, 0])), ref)


@pytest.mark.parametrize("kind", ["controlnet", "omni"])
def test_training_leaves_frozen_base_bit_identical_and_scale_zero_is_base(kind):
    base = base_net()
    before = {k: v.clone() for k, v in base.state_dict().items()}
    m = AdaptedDenoiser(base, AdaptorConfig(kind=kind, labels=["a", "b"]))
    opt = torch.optim.AdamW([p for p in m.parameters() if p.requires_grad], lr=1e-2)
    t, x, x0 = inputs()
    y = torch.tensor([0, 1, 1])
    for _ in range(5):
        loss = (m(t, x, x0, y) - x).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    for k, v in base.state_dict().items():
        assert torch.equal(v, before[k]), k
    m.eval()
    assert not torch.equal(m(t, x, x0, y), base(t, x, x0))  # it learned something
    assert torch.equal(m(t, x, x0, y, scale=0.0), base(t, x, x0))


def test_finetuning_trains_a_copy_and_records_the_base_it_started_from(tmp_path):
    base = base_net()
    before = {k: v.clone() for k, v in base.state_dict().items()}
    m = AdaptedDenoiser(base, AdaptorConfig(kind="finetune", labels=["a", "b"]))
    opt = torch.optim.AdamW(m.parameters(), lr=1e-2)
    t, x, x0 = inputs()
    for _ in range(3):
        loss = (m(t, x, x0, torch.tensor([0, 1, 1])) - x).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert not torch.equal(m.base.out.weight, before["out.weight"])  # the tuned network moved
    for k, v in base.state_dict().items():  # the shared base did not
        assert torch.equal(v, before[k]), k
    save_adaptor(tmp_path / "ft", m.eval(), "base-x")
    shared = base_net()
    ft = load_adaptor(tmp_path / "ft", shared, "base-x")  # its fingerprint is the original base's
    assert torch.equal(ft(t, x, x0, torch.tensor([0, 1, 1])), m(t, x, x0, torch.tensor([0, 1, 1])))
    for k, v in shared.state_dict().items():  # loading it leaves the shared base alone too
        assert torch.equal(v, before[k]), k


def test_targets_and_saving(tmp_path):
    base = base_net()
    m = AdaptedDenoiser(base, AdaptorConfig(control="target"))
    torch.nn.init.normal_(m.zero[0].weight)
    t, x, x0 = inputs()
    y = torch.tensor([[1.5, 0.0], [0.0, -1.0], [0.3, 0.3]])
    out = m.eval()(t, x, x0, y)
    save_adaptor(tmp_path / "a", m, "base-x")
    m2 = load_adaptor(tmp_path / "a", base_net(), "base-x")
    assert torch.equal(m2(t, x, x0, y), out)
    assert not any(k.startswith("base.") for k in m.adaptor_state())  # saved without the base
    with pytest.raises(ValueError, match="trained on base model"):
        load_adaptor(tmp_path / "a", base_net(), "other")
    retrained = base_net()
    with torch.no_grad():
        retrained.out.bias.add_(0.1)  # same name, other weights
    with pytest.raises(ValueError, match="retrain the adaptor"):
        load_adaptor(tmp_path / "a", retrained, "base-x")
    r = rescale_target(torch.tensor([[3.0, 4.0]]))
    assert abs(float(r.norm()) - 2 * (1 - math.exp(-5.0))) < 1e-6


def test_validation():
    with pytest.raises(ValueError, match="kind"):
        AdaptedDenoiser(base_net(), AdaptorConfig(kind="lora", labels=["a"]))
    with pytest.raises(ValueError, match="at least one label"):
        AdaptedDenoiser(base_net(), AdaptorConfig(labels=[]))


@pytest.mark.parametrize("task", ["actions", "reach"])
def test_adapt_command_trains_and_saves(tmp_path, task):
    import shutil
    from avatar_motor.cli import main
    from avatar_motor.data.cache import import_motion
    from avatar_motor.model.checkpoint import load_checkpoint
    from .conftest_models import tiny_motor
    from .fixture_tools import FIXTURES
    tiny_motor(tmp_path)
    src = tmp_path / "clips"
    src.mkdir()
    for name, content in (("walk_lafan1", "walk"), ("walk_cmu", "wave"), ("walk_mixamo", "walk")):
        shutil.copy(FIXTURES / f"{name}.bvh", src / f"dataset-9_{content}_normal_00{len(list(src.iterdir()))}.bvh")
    import_motion(src, name="labelled", progress=False, workers=1)
    def sets(**kv):
        return [a for k, v in kv.items() for a in ("--set", f"{k}={json.dumps(v)}")]

    args = ["adapt", *sets(task=task, base=str(tmp_path / "tiny"), data=["labelled"], steps=3, batch=4,
                           out=str(tmp_path / "ad"), split="all")]
    if task == "actions":
        args += sets(swap_initial=1.0)  # every window of another class's state swaps: the path runs
    assert main(args) == 0
    m = load_adaptor(tmp_path / "ad" / "adaptor", load_checkpoint(tmp_path / "tiny").net)
    assert m.cfg.control == ("label" if task == "actions" else "target")
    if task == "actions":
        assert m.cfg.labels == ["walk", "wave"]
        assert json.loads((tmp_path / "ad" / "adapt_config.json").read_text())["swap_initial"] == 1.0
        # an action's handedness is kept (no mirrored windows) unless asked for
        assert json.loads((tmp_path / "ad" / "adaptor" / "adaptor.json").read_text())["mirror"] is False
        assert main(args + sets(classes=["dance"])) == 2  # unknown class named
        assert main(args + sets(swap_initial=1.5)) == 2  # a swap fraction above 1
        # the neighbour swap runs end to end (partners of another class found among near states)
        assert main(args + sets(swap_neighbours=4, out=str(tmp_path / "nn"))) == 0
        meta = json.loads((tmp_path / "nn" / "adaptor" / "adaptor.json").read_text())
        assert meta["swap_neighbours"] == 4 and meta["mirror"] is False
        assert main(args + sets(swap_neighbours=4, swap_match="feet", out=str(tmp_path / "feet"))) == 0
        assert json.loads((tmp_path / "feet" / "adaptor" / "adaptor.json").read_text())["swap_match"] == "feet"
        assert main(args + sets(swap_match="feet")) == 2  # nothing to match without the neighbour search
        # swapped-in states from another cache (it holds only walks, so wave windows can get its
        # states and walk windows none), by itself and with the neighbour search over that cache
        walks = tmp_path / "walks"
        walks.mkdir()
        shutil.copy(FIXTURES / "walk_lafan1.bvh", walks / "dataset-9_walk_normal_100.bvh")
        import_motion(walks, name="walks", progress=False, workers=1)
        for k in ("0", "4"):
            assert main(args + sets(swap_data=["walks"], swap_neighbours=int(k), out=str(tmp_path / f"sd{k}"))) == 0
            assert json.loads((tmp_path / f"sd{k}" / "adaptor" / "adaptor.json").read_text())["swap_data"] == ["walks"]
        assert main(args + sets(swap_data=["no-such-cache"])) == 2
        assert main(args + sets(swap_initial=0, swap_data=["walks"])) == 2  # nothing would be swapped in
        assert main(args + sets(mirror=True, out=str(tmp_path / "mirrored"))) == 0
        assert json.loads((tmp_path / "mirrored" / "adaptor" / "adaptor.json").read_text())["mirror"] is True
        assert main(args + sets(swap_neighbours=-1)) == 2
        assert main(args + sets(no_such_field=1)) == 2  # a misspelt field is named, not ignored
        # Table A3 end to end: the evaluator, the table and the confusion matrix. Its initial states
        # come from held-out clips: add one (a file name whose hash falls in the held-out split)
        from avatar_motor.data.cache import is_held_out
        held = next(f"dataset-9_walk_normal_{k:03d}.bvh" for k in range(1000) if is_held_out(f"dataset-9_walk_normal_{k:03d}.bvh"))
        shutil.copy(FIXTURES / "walk_lafan1.bvh", src / held)
        import_motion(src, name="labelled", progress=False, workers=1)
        assert main(["eval", "actions", "--model", str(tmp_path / "tiny"), "--adaptors", f"ours={tmp_path / 'ad' / 'adaptor'}",
                     "--data", "labelled", "--n", "2", "--seconds", "1", "--encoder-steps", "2"]) == 0
    else:
        assert main(args + sets(ema_decay=1.0)) == 2  # an average that never moves is named
        assert json.loads((tmp_path / "ad" / "adaptor" / "adaptor.json").read_text())["mirror"] is True  # targets have no hand
        # the scratch baseline loads beside the base it was compared with (its fingerprint is that base's)
        assert main(args + sets(out=str(tmp_path / "scratch"), kind="finetune", scratch=True)) == 0  # the last --set counts
        load_adaptor(tmp_path / "scratch" / "adaptor", load_checkpoint(tmp_path / "tiny").net)
        # the saved weights are the moving average: from the zero-initialised projections it
        # moves less far than the last weights of the same run
        from avatar_motor.train.adapt import AdaptConfig, adapt
        net = load_checkpoint(tmp_path / "tiny").net
        norms = {}
        for decay in (0.0, 0.9):
            cfg = AdaptConfig(base=str(tmp_path / "tiny"), data=["labelled"], task="reach", steps=3, batch=4, split="all",
                              out=str(tmp_path / f"ema{decay}"), ema_decay=decay, ema_start=0)
            ad = load_adaptor(adapt(cfg, progress=False), net)
            norms[decay] = sum(float(p.detach().norm()) for p in ad.zero.parameters())
        assert 0 < norms[0.9] < norms[0.0]
        # a cosine schedule takes smaller steps as it goes: the same run ends nearer its start
        cfg = AdaptConfig(base=str(tmp_path / "tiny"), data=["labelled"], task="reach", steps=3, batch=4, split="all",
                          out=str(tmp_path / "cosine"), ema_decay=0.0, lr_schedule="cosine")
        ad = load_adaptor(adapt(cfg, progress=False), net)
        assert 0 < sum(float(p.detach().norm()) for p in ad.zero.parameters()) < norms[0.0]


def test_the_best_reaching_run_is_the_nearest_that_skates_within_the_bound():
    from avatar_motor.eval.adaptation import best_reaching
    rows = [{"method": "base", "min_dist_m": 1.1, "ASR": 0.0}, {"method": "s0", "min_dist_m": 0.030, "ASR": 0.090},
            {"method": "s1", "min_dist_m": 0.040, "ASR": 0.050}, {"method": "s2", "min_dist_m": 0.035, "ASR": 0.060}]
    assert best_reaching(rows) == (rows[3], True)  # s0 is nearer but skates beyond 0.070
    assert best_reaching(rows, asr_bound=0.1) == (rows[1], True)
    assert best_reaching(rows, asr_bound=0.01) == (rows[1], False)  # none within: the nearest, said so
    assert best_reaching(rows, asr_bound=0.060) == (rows[3], True)  # the bound itself is within
    broken = [{"method": "nan", "min_dist_m": float("nan"), "ASR": 0.0}] + rows
    assert best_reaching(broken) == (rows[3], True)  # a run that diverged is never chosen
    with pytest.raises(ValueError, match="besides the base"):
        best_reaching(rows[:1])


def test_eval_reach_keeps_the_run_nearest_its_targets(tmp_path, capsys):
    """make models trains the reaching recipe with three seeds and ships the one `eval reach
    --keep-best` chooses (on other initial states than its figures): the copy loads as the chosen
    run, records the choice, ships with it, and the command refuses to write over a candidate."""
    import shutil
    from avatar_motor.cli import main
    from avatar_motor.data.cache import import_motion, is_held_out
    from avatar_motor.model.checkpoint import load_checkpoint
    from .conftest_models import tiny_motor
    from .fixture_tools import FIXTURES
    tiny_motor(tmp_path)
    src = tmp_path / "clips"
    src.mkdir()
    held = next(f"dataset-9_walk_normal_{k:03d}.bvh" for k in range(1000) if is_held_out(f"dataset-9_walk_normal_{k:03d}.bvh"))
    for name, file in (("walk_lafan1", "dataset-9_walk_normal_001.bvh"), ("walk_cmu", held)):
        shutil.copy(FIXTURES / f"{name}.bvh", src / file)
    import_motion(src, name="clips", progress=False, workers=1)
    ads = []
    for seed in (0, 1):
        out = tmp_path / f"reach-{seed}"
        assert main(["adapt", "--set", "task=reach", "--set", f"base={tmp_path / 'tiny'}", "--set", 'data=["clips"]',
                     "--set", "steps=2", "--set", "batch=4", "--set", "split=all", "--set", f"seed={seed}",
                     "--set", f"out={out}"]) == 0
        ads.append(f"s{seed}={out / 'adaptor'}")
    kept = tmp_path / "kept"
    args = ["eval", "reach", "--model", str(tmp_path / "tiny"), "--data", "clips", "--n", "1", "--seconds", "0.5",
            "--seed", "1", "--adaptor-scale", "2.5", "--adaptors", *ads, "--keep-best"]
    assert main(args + [str(kept)]) == 0
    meta = json.loads((kept / "adaptor.json").read_text())
    sel = meta["selection"]
    assert set(sel["candidates"]) == {"s0", "s1"} and sel["seed"] == 1 and sel["asr_bound"] == 0.070
    from avatar_motor.eval.adaptation import best_reaching
    recorded = [{"method": k, **v} for k, v in sel["candidates"].items()]
    assert best_reaching(recorded)[0]["method"] == sel["chosen"] and sel["within_bound"] == best_reaching(recorded)[1]
    assert sel["adaptor_scale"] == 2.5 and meta["scale"] == 2.5  # its avatars get the scale it was chosen at
    chosen = tmp_path / f"reach-{sel['chosen'][1]}" / "adaptor"
    assert (kept / "adaptor.safetensors").read_bytes() == (chosen / "adaptor.safetensors").read_bytes()
    net = load_checkpoint(tmp_path / "tiny").net
    load_adaptor(kept, net)
    assert main(["ship", str(kept), str(tmp_path / "shipped"), "--base", str(tmp_path / "tiny")]) == 0
    assert json.loads((tmp_path / "shipped" / "adaptor.json").read_text())["selection"] == sel
    # a candidate, or a folder holding one, is never replaced (refused before any rollout)
    before = (tmp_path / "reach-0" / "adaptor" / "adaptor.safetensors").read_bytes()
    def refused(argv) -> str:
        capsys.readouterr()
        assert main(argv) == 2
        return capsys.readouterr().err
    for out in (tmp_path / "reach-0" / "adaptor", tmp_path / "reach-0", tmp_path):
        err = refused(args + [str(out)])
        assert "would replace the adaptor s0" in err and "reaching (Table A4)" not in err
    assert (tmp_path / "reach-0" / "adaptor" / "adaptor.safetensors").read_bytes() == before
    assert "'base' names the unadapted model's row" in refused(
        args[:-2] + [f"base={tmp_path / 'reach-0' / 'adaptor'}", "--keep-best", str(tmp_path / "k2")])
    assert "'s0' is given twice" in refused(args[:-1] + [ads[0], "--keep-best", str(tmp_path / "k2")])


def test_cosine_schedule_runs_on_steps_or_on_wall_time():
    from avatar_motor.train.adapt import AdaptConfig, _progress
    assert _progress(50, AdaptConfig(steps=100), seconds=1e6) == 0.5  # no time limit: steps count
    timed = AdaptConfig(steps=100000, max_minutes=10)
    assert _progress(50, timed, seconds=300) == 0.5  # a time-limited run: the clock counts
    assert _progress(50, timed, seconds=900) == 1.0
    with pytest.raises(ValueError, match="lr_schedule"):
        from avatar_motor.train.adapt import adapt
        adapt(AdaptConfig(lr_schedule="step"), progress=False)


def test_a_reaching_avatar_faces_its_target_until_it_is_near(tmp_path):
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import tiny_motor
    motor = tiny_motor(tmp_path)
    ad = AdaptedDenoiser(motor.net, AdaptorConfig(control="target")).eval()
    crowd = Crowd(motor, RuntimeConfig(face_target_beyond=0.5), adaptors=ad)
    i = crowd.spawn(position=(1.0, 2.0))
    a = crowd.avatars[i]
    assert crowd._facing_goal(a) is None  # no target, no facing goal
    crowd.set_target(i, (1.0 - 3.0, 2.0 + 4.0))
    pelvis = a.state[135:201].view(22, 3)[0, [0, 2]]
    way = torch.tensor([-3.0, 4.0]) + torch.tensor([1.0, 2.0]) - pelvis
    assert torch.allclose(crowd._facing_goal(a)[[0, 2]], way / way.norm(), atol=1e-6)
    crowd.set_target(i, (float(pelvis[0]) + 0.3, float(pelvis[1])))
    assert crowd._facing_goal(a) is None  # near: it may step there any way it likes
    a.target = pelvis + torch.tensor([0.8, 0.0])  # the target drifts off a little: still near (hysteresis)
    assert crowd._facing_goal(a) is None
    a.target = pelvis + torch.tensor([1.2, 0.0])  # beyond twice the threshold: faced again
    assert torch.allclose(crowd._facing_goal(a), torch.tensor([1.0, 0.0, 0.0]))
    crowd.set_goal(i, (0.0, 1.0), facing=(1.0, 0.0))
    assert torch.allclose(crowd._facing_goal(a), torch.tensor([1.0, 0.0, 0.0]))  # a user's facing goal wins


def test_a_reaching_avatar_near_its_target_is_walked_onto_it_and_stopped(tmp_path):
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import tiny_motor
    motor = tiny_motor(tmp_path)
    ad = AdaptedDenoiser(motor.net, AdaptorConfig(control="target")).eval()
    crowd = Crowd(motor, RuntimeConfig(arrive_within=0.5, arrive_time=0.5), adaptors=ad)
    i = crowd.spawn(position=(1.0, 2.0))
    a = crowd.avatars[i]
    pelvis = a.state[135:201].view(22, 3)[0, [0, 2]]
    assert crowd._velocity_goal(a) is None  # no target, no velocity goal
    crowd.set_target(i, (float(pelvis[0]) + 2.0, float(pelvis[1])))
    assert crowd._velocity_goal(a) is None  # far: the adaptor and the facing goal take it there
    crowd.set_target(i, (float(pelvis[0]) + 0.3, float(pelvis[1]) - 0.2))
    assert torch.allclose(crowd._velocity_goal(a), torch.tensor([0.6, 0.0, -0.4]), atol=1e-5)  # (target - pelvis) / 0.5 s
    crowd.set_target(i, (float(pelvis[0]), float(pelvis[1])))
    assert torch.allclose(crowd._velocity_goal(a), torch.zeros(3), atol=1e-6)  # on it: stop
    assert Crowd(motor, RuntimeConfig(arrive_within=0.0), adaptors=ad)._velocity_goal(a) is None  # off
    crowd.set_goal(i, (0.0, 1.0))
    assert torch.allclose(crowd._velocity_goal(a), torch.tensor([0.0, 0.0, 1.0]))  # a user's velocity goal wins


def test_nearest_candidate_picks_the_segment_ending_nearest_the_target():
    from avatar_motor.runtime.processing import nearest_candidate
    from avatar_motor.runtime.crowd import standing_state
    x = standing_state().double()
    cands = x.expand(2, 3, 15, 267).clone()  # 2 avatars x 3 candidates of 15 frames
    ends = torch.tensor([[[0.0, 1.0], [0.4, 0.1], [2.0, 0.0]], [[3.0, 3.0], [0.9, 0.8], [1.0, 1.0]]])
    pelvis = slice(135, 138)
    for a in range(2):
        for k in range(3):
            cands[a, k, 7, pelvis][[0, 2]] = torch.tensor([0.5, 0.0], dtype=torch.float64)  # passing the target mid-way does not count
            cands[a, k, -1, pelvis][[0, 2]] = ends[a, k].double()
    targets = torch.tensor([[0.5, 0.0], [1.0, 1.0]])
    assert nearest_candidate(cands, targets).tolist() == [1, 2]
    # a penalty (the metres a wall moved each candidate) is added to the distance; without a
    # target (NaN) it alone decides
    penalty = torch.tensor([[0.0, 2.0, 0.0], [0.3, 0.0, 0.5]])
    assert nearest_candidate(cands, targets, penalty).tolist() == [0, 1]
    assert nearest_candidate(cands, torch.full((2, 2), float("nan")), penalty).tolist() == [0, 1]


def test_a_reaching_avatar_shows_the_nearest_of_its_candidates(tmp_path):
    """reach_candidates K: a reaching avatar's segment is the one of its K draws (processed as any
    segment is) that ends nearest its target; an avatar without a target gets one draw, as with
    K = 1, and a run is the same for the same seed."""
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import tiny_motor
    motor = tiny_motor(tmp_path)
    ad = AdaptedDenoiser(motor.net, AdaptorConfig(control="target")).eval()
    torch.nn.init.normal_(ad.zero[0].weight, std=0.5)
    target = torch.tensor([0.0, 1.5])
    seen = []

    def run(K, seed=2):
        crowd = Crowd(motor, RuntimeConfig(reach_candidates=K), seed=seed, adaptors=ad)
        choose = crowd._choose_nearest

        def spy(batch, plain, counts, seg, moved=None):
            out = choose(batch, plain, counts, seg, moved)
            seen.append((counts, seg, out))
            return out
        crowd._choose_nearest = spy
        i, j = crowd.spawn(), crowd.spawn(position=(2.0, 0.0))
        crowd.set_target(i, target.tolist())
        return crowd.step_segment(), i, j

    one, i, j = run(1)
    assert not seen  # one draw each: nothing to choose
    four, _, _ = run(4)
    (counts, seg, out), = seen
    assert counts == [4, 1]  # avatar i (the first spawned) has the target
    ends = (seg[:4, -1, 135:138][:, [0, 2]] - target.double()).norm(dim=-1)
    assert torch.equal(out[0], seg[int(ends.argmin())])
    assert torch.allclose(four[i], out[0].float())
    assert len({round(float(e), 6) for e in ends}) == 4  # four different draws
    assert torch.allclose(four[j], one[j], atol=1e-5)  # the avatar without a target: as before
    again, _, _ = run(4)
    assert torch.equal(again[i], four[i])


def test_an_avatar_with_a_velocity_goal_shows_the_candidate_ending_where_the_goal_takes_it(tmp_path):
    """goal_candidates K: the candidate whose pelvis ends nearest x0's pelvis moved along the goal's
    path (its velocity approaching the goal with trajectory_halflife) over the segment."""
    import math
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from .conftest_models import tiny_motor
    motor = tiny_motor(tmp_path)
    crowd = Crowd(motor, RuntimeConfig(goal_candidates=3, trajectory_halflife=0.2), seed=4)
    seen = []
    choose = crowd._choose_nearest
    crowd._choose_nearest = lambda *args: seen.append(args) or choose(*args)
    i = crowd.spawn()
    crowd.set_goal(i, (0.0, 1.2))
    x0 = crowd.state(i).double()
    shown = crowd.step_segment()[i]
    (batch, plain, counts, seg, moved), = seen
    assert moved is None  # no obstacle: nothing slid
    assert counts == [3]
    T, lam = seg.shape[1] / 30.0, math.log(2) / 0.2
    v0 = x0[201:267].view(22, 3)[0, [0, 2]]
    vg = torch.tensor([0.0, 1.2], dtype=torch.float64)
    wanted = x0[135:201].view(22, 3)[0, [0, 2]] + vg * T + (v0 - vg) / lam * (1 - math.exp(-lam * T))
    ends = (seg[:, -1, 135:138][:, [0, 2]] - wanted).norm(dim=-1)
    assert torch.allclose(shown, seg[int(ends.argmin())].float())
    assert len({round(float(e), 6) for e in ends}) == 3


def test_runtime_labels_and_targets(tmp_path):
    from avatar_motor.runtime.crowd import Crowd
    from .conftest_models import tiny_motor
    motor = tiny_motor(tmp_path)
    ad = AdaptedDenoiser(motor.net, AdaptorConfig(labels=["walk", "wave"])).eval()
    torch.nn.init.normal_(ad.zero[0].weight, std=0.5)
    crowd = Crowd(motor, seed=1, adaptors=ad)
    plain = Crowd(motor, seed=1)
    i, j = crowd.spawn(), plain.spawn()
    assert torch.equal(crowd.step_segment()[i], plain.step_segment()[j])  # no label: the base model exactly
    crowd.set_label(i, "wave")
    assert not torch.equal(crowd.step_segment()[i], plain.step_segment()[j])
    with pytest.raises(ValueError, match="unknown label 'dance'"):
        crowd.set_label(i, "dance")
    with pytest.raises(ValueError, match="no reaching adaptor"):
        crowd.set_target(i, (1.0, 2.0))
    with pytest.raises(ValueError, match="no action adaptor"):
        plain.set_label(j, "walk")
    reach = Crowd(motor, adaptors=AdaptedDenoiser(motor.net, AdaptorConfig(control="target")).eval())
    k = reach.spawn()
    reach.set_target(k, (2.0, 1.0))
    assert reach.step_segment()[k].shape == (15, 267)
    with pytest.raises(ValueError, match="finite"):
        reach.set_target(k, (float("nan"), 1.0))
    with pytest.raises(ValueError, match=r"adaptor scale must be in \[0, 10\]"):
        reach.set_target(k, (2.0, 1.0), scale=-1.0)
    # a target at scale 0 is the base model exactly (classifier-free guidance weight 0)
    torch.nn.init.normal_(reach.adaptors[0].zero[0].weight, std=0.5)
    base = Crowd(motor)
    b = base.spawn()
    zero = Crowd(motor, adaptors=reach.adaptors)
    z = zero.spawn()
    zero.set_target(z, (2.0, 1.0), scale=0.0)
    assert torch.equal(zero.step_segment()[z], base.step_segment()[b])


def test_several_adaptors_steer_their_own_avatars(tmp_path):
    """Actions, styles and reaching loaded together: a label picks the adaptor that knows it, a
    target the reaching one, the latest command replaces the other; in one batch each avatar gets
    what it would get alone with its adaptor, and the unsteered one the base model."""
    from avatar_motor.runtime.crowd import Crowd
    from .conftest_models import tiny_motor
    motor = tiny_motor(tmp_path)
    ads = [AdaptedDenoiser(motor.net, AdaptorConfig(labels=["bow", "wave"])).eval(),
           AdaptedDenoiser(motor.net, AdaptorConfig(labels=["tired", "proud"])).eval(),
           AdaptedDenoiser(motor.net, AdaptorConfig(control="target")).eval()]
    for ad in ads:
        torch.nn.init.normal_(ad.zero[0].weight, std=0.5)
    crowd = Crowd(motor, seed=3, adaptors=ads)
    ids = [crowd.spawn(position=(float(k), 0.0)) for k in range(4)]
    crowd.set_label(ids[0], "wave")
    crowd.set_label(ids[1], "proud")
    crowd.set_target(ids[2], (2.0, 1.0))
    a = crowd.avatars
    assert (a[ids[0]].adaptor, a[ids[0]].label, a[ids[1]].adaptor, a[ids[1]].label, a[ids[2]].adaptor) == (0, 1, 1, 1, 2)
    together = crowd.step_segment()
    for k, (ad, setup) in enumerate(((ads[0], lambda c, i: c.set_label(i, "wave")), (ads[1], lambda c, i: c.set_label(i, "proud")),
                                     (ads[2], lambda c, i: c.set_target(i, (2.0, 1.0))), (None, lambda c, i: None))):
        alone = Crowd(motor, seed=3, adaptors=ad)
        for m in range(k):  # same ids, so the same noise streams
            alone.spawn(position=(float(m), 0.0))
        i = alone.spawn(position=(float(k), 0.0))
        setup(alone, i)
        got = alone.step_segment()[i]
        assert torch.allclose(got, together[ids[k]], atol=1e-4, rtol=1e-4), (k, float((got - together[ids[k]]).abs().max()))
    crowd.set_target(ids[0], (1.0, 1.0))  # a target replaces the label
    assert (a[ids[0]].adaptor, a[ids[0]].label) == (2, None)
    crowd.set_label(ids[2], "bow")  # and a label the target
    assert (a[ids[2]].adaptor, a[ids[2]].target) == (0, None)
    crowd.set_target(ids[2], None)  # releasing what is not set leaves the label alone
    assert a[ids[2]].adaptor == 0
    crowd.set_label(ids[2], None)
    assert a[ids[2]].adaptor is None and not a[ids[2]].adapted
    crowd.reset(ids[1])  # every control released, the adaptor with its label
    assert a[ids[1]].adaptor is None and a[ids[1]].label is None and not a[ids[1]].adapted
    with pytest.raises(ValueError, match=r"unknown label 'dance'; the loaded adaptors know \['bow', 'proud', 'tired', 'wave'\]"):
        crowd.set_label(ids[3], "dance")


def test_shipped_adaptors_are_found_for_their_base(tmp_path):
    from avatar_motor.model.adaptor import shipped_adaptors
    from avatar_motor.model.checkpoint import load_checkpoint
    from .conftest_models import tiny_motor
    motor = tiny_motor(tmp_path)
    models = tmp_path / "models"
    save_adaptor(models / "tiny-actions", AdaptedDenoiser(motor.net, AdaptorConfig(labels=["a"])), motor.name)
    other = load_checkpoint(tmp_path / "tiny").net
    torch.nn.init.normal_(other.out.weight if hasattr(other, "out") else next(other.parameters()), std=0.1)
    save_adaptor(models / "other-actions", AdaptedDenoiser(other, AdaptorConfig(labels=["a"])), motor.name)
    (models / "broken").mkdir()
    (models / "broken" / "adaptor.json").write_text("{not json")
    assert shipped_adaptors(models, motor) == [models / "tiny-actions"]
    assert load_adaptor(models / "tiny-actions", motor.net).name == "tiny-actions"
    # `ship`: float16, named for its folder, its card written once and kept on a re-ship
    from safetensors.torch import load_file
    from avatar_motor.cli import main
    assert main(["ship", str(models / "tiny-actions"), str(models / "tiny-styles"), "--base", str(tmp_path / "tiny")]) == 0
    assert {v.dtype for v in load_file(str(models / "tiny-styles" / "adaptor.safetensors")).values()} == {torch.float16}
    assert "non-commercial" in (models / "tiny-styles" / "card.md").read_text()
    (models / "tiny-styles" / "card.md").write_text("# hand-written\n")
    assert main(["ship", str(models / "tiny-actions"), str(models / "tiny-styles"), "--base", str(tmp_path / "tiny")]) == 0
    assert (models / "tiny-styles" / "card.md").read_text() == "# hand-written\n"
    assert load_adaptor(models / "tiny-styles", motor.net).name == "tiny-styles"
    assert shipped_adaptors(models, motor) == [models / "tiny-actions", models / "tiny-styles"]
    # an adaptor shipped onto another base's weights is refused, naming the fix
    assert main(["ship", str(models / "other-actions"), str(models / "x"), "--base", str(tmp_path / "tiny")]) == 2


def test_adaptation_evals_run_on_tiny_models(tmp_path, caplog):
    from avatar_motor.data.cache import MotionCache, import_motion
    from avatar_motor.data.dataset import SegmentConfig, SegmentDataset
    from avatar_motor.eval.adaptation import eval_actions, eval_reach, predict_labels, train_evaluators
    from .conftest_models import tiny_motor
    from .fixture_tools import FIXTURES
    import shutil
    motor = tiny_motor(tmp_path)
    src = tmp_path / "clips"
    src.mkdir()
    for k, (name, content) in enumerate((("walk_lafan1", "walk"), ("walk_cmu", "wave"))):
        shutil.copy(FIXTURES / f"{name}.bvh", src / f"dataset-9_{content}_normal_00{k}.bvh")
    path, _ = import_motion(src, name="labelled", progress=False, workers=1)
    ds = SegmentDataset([MotionCache.load(path)], SegmentConfig(frames=30, split="all"))
    encs = train_evaluators(ds, "content", ["walk", "wave"], seconds=1.0, steps=5, seeds=[0, 1])
    init, shapes = ds.sample(2, torch.Generator().manual_seed(0))
    ad = AdaptedDenoiser(motor.net, AdaptorConfig(labels=["walk", "wave"])).eval()
    rows, rollouts = eval_actions(motor, {"base": None, "ours": ad}, encs, init[:, 0], shapes, ["walk", "wave"], seconds=1.0)
    assert [r["method"] for r in rows] == ["base", "ours"]
    r = rows[1]
    assert 0 <= r["R_min"] <= r["R_precision"] <= r["R_max"] <= 1
    # the averaged confusion holds each evaluator's reading of every rollout once: 2 per label
    assert [sum(row) for row in r["confusion"]] == pytest.approx([2.0, 2.0])
    X = torch.cat([rollouts["ours"]["walk"], rollouts["ours"]["wave"]])
    y = torch.tensor([0, 0, 1, 1])
    by_each = [float((predict_labels(*e, X) == y).float().mean()) for e in encs]
    assert r["R_precision"] == pytest.approx(sum(by_each) / 2) and r["R_max"] == max(by_each)
    # stored evaluators are read back as they were; a damaged one is trained again, not trusted
    said = []
    first = train_evaluators(ds, "content", ["walk", "wave"], 1.0, 5, [3], said.append, cache=tmp_path / "ev")
    again = train_evaluators(ds, "content", ["walk", "wave"], 1.0, 5, [3], said.append, cache=tmp_path / "ev")
    assert "training" in said[0] and "ev" in said[-1] and torch.equal(
        first[0][0](X[:, :30, :66].float()), again[0][0](X[:, :30, :66].float()))
    stored = next((tmp_path / "ev").glob("*.pt"))
    stored.write_bytes(b"not a checkpoint")
    train_evaluators(ds, "content", ["walk", "wave"], 1.0, 5, [3], said.append, cache=tmp_path / "ev")
    assert "unreadable" in said[-2] and "training" in said[-1]
    assert len(list((tmp_path / "ev").iterdir())) == 1 and stored.stat().st_size > 1000
    assert rollouts["ours"]["wave"].shape == (2, 31, 267)
    reach = AdaptedDenoiser(motor.net, AdaptorConfig(control="target")).eval()
    rows, paths = eval_reach(motor, {"base": None, "ours": reach}, init[:, 0], shapes, seconds=0.5)
    assert 0 < rows[1]["min_dist_m"] <= rows[1]["final_dist_m"] and paths["ours"].shape == (8, 2, 16, 2)
    per = rows[1]["per_target_m"]  # each target's mean, in TARGETS' order: the paths' nearest approach
    assert len(per) == 8 and abs(sum(per) / 8 - rows[1]["min_dist_m"]) < 1e-6
    from avatar_motor.eval.adaptation import TARGETS as T
    assert abs(per[0] - float((paths["ours"][0] - torch.tensor(T[0])).norm(dim=-1).amin(-1).mean())) < 1e-3
    from avatar_motor.viz import label_grid, target_paths
    from avatar_motor.eval.adaptation import TARGETS, canonical_joints
    clips = {k: [canonical_joints(X[i:i + 1])[0].reshape(-1, 22, 3).numpy() for i in range(len(X))] for k, X in rollouts["ours"].items()}
    with caplog.at_level(logging.WARNING):
        label_grid(clips, tmp_path / "grid.png")
    assert not caplog.records, "the grid once logged a matplotlib warning per cell (fixed limits vs equal aspect)"
    target_paths({k: v.numpy() for k, v in paths.items()}, TARGETS, tmp_path / "paths.png")
    assert (tmp_path / "grid.png").stat().st_size > 1000 and (tmp_path / "paths.png").stat().st_size > 1000


@pytest.mark.parametrize("kind", ["controlnet", "omni", "finetune"])
def test_scale_per_row_as_the_runtime_passes_it(kind):
    # the crowd passes one scale per avatar (B, 1, 1): 0 where no label is set
    base = base_net()
    m = AdaptedDenoiser(base, AdaptorConfig(kind=kind, labels=["a", "b"])).eval()
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.01)  # an adaptor that changes the output (zero projections no longer zero)
    t, x, x0 = inputs()
    y = torch.tensor([0, 1, 1])
    out = m(t, x, x0, y, scale=torch.tensor([0.0, 1.0, 2.0]).view(3, 1, 1))
    assert out.shape == x.shape
    for k, s in enumerate([0.0, 1.0, 2.0]):
        assert torch.allclose(out[k], m(t[k:k + 1], x[k:k + 1], x0[k:k + 1], y[k:k + 1], scale=s)[0], atol=1e-5)


@pytest.mark.parametrize("kind,control", [("controlnet", "label"), ("omni", "target"), ("finetune", "label")])
def test_scale_above_one_is_classifier_free_guidance(kind, control):
    # Eq. (3): G(null) + gamma (G(y) - G(null)), the unconditional model being the adaptor with the
    # null control; at 1 both readings are the trained adaptor, so the scale is continuous there
    m = AdaptedDenoiser(base_net(), AdaptorConfig(kind=kind, control=control, labels=["a", "b"])).eval()
    m.guidance = "null"  # PRIMAL's (the target adaptor's only)
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.01)
    t, x, x0 = inputs()
    y = torch.tensor([0, 1, 1]) if control == "label" else torch.tensor([[1.0, 0.5], [-2.0, 0.0], [0.0, 3.0]])
    with torch.no_grad():
        cond = m(t, x, x0, y, scale=1.0)
        null = m(t, x, x0, y, scale=1.0, drop=torch.ones(3, dtype=torch.bool))
        assert not torch.allclose(cond, null)
        for gamma in (1.5, 3.0):
            assert torch.allclose(m(t, x, x0, y, scale=gamma), null + gamma * (cond - null), atol=1e-5)
        assert torch.allclose(m(t, x, x0, y, scale=1.0 + 1e-6), cond, atol=1e-4)
        # rows guided and not in one batch (the null control's pass joins the rows' own) read as alone
        mixed = m(t, x, x0, y, scale=torch.tensor([0.5, 1.0, 2.5]).view(3, 1, 1))
        for k, s in enumerate([0.5, 1.0, 2.5]):
            assert torch.allclose(mixed[k], m(t[k:k + 1], x[k:k + 1], x0[k:k + 1], y[k:k + 1], scale=s)[0], atol=1e-5)


def test_neighbour_swap_partners_are_near_states_of_other_clips():
    from avatar_motor.train.adapt import _NeighbourPool
    pool = object.__new__(_NeighbourPool)  # the search alone, on made-up features
    pool.feats = torch.tensor([[0.0], [0.1], [0.2], [5.0], [5.1]])
    pool.clip = torch.tensor([0, 1, 2, 3, 4])
    pool.features = lambda x: x
    g = torch.Generator().manual_seed(0)
    picks = {int(pool.partners(torch.tensor([[0.0]]), torch.tensor([0]), 2, g)) for _ in range(40)}
    assert picks == {1, 2}  # the two nearest, never its own clip (0), never the far ones
    odd = (pool.clip % 2 == 1)[None]  # e.g. "of another class"
    picks = {int(pool.partners(torch.tensor([[0.0]]), torch.tensor([0]), 2, g, odd)) for _ in range(40)}
    assert picks == {1, 3}


def test_feet_matching_compares_only_the_ankles_and_feet():
    from avatar_motor.body.motion_state import SLICES, STATE_DIM
    from avatar_motor.train.adapt import _match_features
    feet, state = _match_features("feet"), _match_features("state")
    assert len(feet) == 2 * 4 * 3 and len(state) == 2 * 22 * 3 and set(feet.tolist()) <= set(state.tolist())
    x = torch.zeros(STATE_DIM)
    x[SLICES["joints"]] = torch.arange(66.0)  # joint j's x, y, z hold 3j, 3j + 1, 3j + 2
    # the left/right ankle (7, 8) and foot (10, 11) positions, then their velocities (zero here)
    assert x[feet[:12]].tolist() == [float(v) for j in (7, 8, 10, 11) for v in range(3 * j, 3 * j + 3)]
    assert (feet[12:] >= SLICES["velocities"].start).all()


def _yaw_locks_seen(monkeypatch) -> list:
    """Records, per segment, which bodies foot locking is asked to hold against yaw (the stages'
    context says it; they may run as a traced graph, which calls no Python function)."""
    from avatar_motor.runtime.stages import StageContext
    seen = []
    real = StageContext.of.__func__

    def of(cls, *a, **k):
        ctx = real(cls, *a, **k)
        seen.append(ctx.lock_yaw.tolist())
        return ctx
    monkeypatch.setattr(StageContext, "of", classmethod(of))
    return seen


def test_a_reaching_avatar_near_its_target_keeps_the_yaw_lock(tmp_path, monkeypatch):
    # near its target it has no facing goal, but it still must not twist on both planted feet
    # (measured, eval reach: ASR 0.106 -> 0.081 at the same distance)
    from avatar_motor.runtime import crowd as crowd_module
    from .conftest_models import tiny_motor
    seen = _yaw_locks_seen(monkeypatch)
    motor = tiny_motor(tmp_path)
    crowd = crowd_module.Crowd(motor, adaptors=AdaptedDenoiser(motor.net, AdaptorConfig(control="target")).eval())
    near, idle = crowd.spawn(position=(0.0, 0.0)), crowd.spawn(position=(3.0, 0.0))
    crowd.set_target(near, (0.1, 0.1))
    crowd.step_segment()
    # (each of the reaching avatar's candidate segments is processed alike)
    assert crowd._facing_goal(crowd.avatars[near]) is None and seen[-1] == [True] * crowd.cfg.reach_candidates + [False]


def test_an_avatar_with_an_action_label_gets_the_yaw_lock(tmp_path, monkeypatch):
    # an action adaptor's turn from a foreign state skates (eval actions: ASR in the first second
    # 0.15-0.25), partly by twisting on both planted feet; at scale 0 it is the base model, unlocked
    from avatar_motor.runtime import crowd as crowd_module
    from .conftest_models import tiny_motor
    seen = _yaw_locks_seen(monkeypatch)
    motor = tiny_motor(tmp_path)
    adaptor = AdaptedDenoiser(motor.net, AdaptorConfig(control="label", labels=["bow", "wave"])).eval()
    crowd = crowd_module.Crowd(motor, adaptors=adaptor)
    labelled, idle = crowd.spawn(position=(0.0, 0.0)), crowd.spawn(position=(3.0, 0.0))
    crowd.set_label(labelled, "bow")
    crowd.step_segment()
    assert seen[-1] == [True, False]
    crowd.set_label(labelled, "bow", 0.0)
    crowd.step_segment()
    assert seen[-1] == [False, False]
    crowd.set_label(labelled, "bow")
    crowd.reset(labelled)  # every control released
    assert crowd.avatars[labelled].label is None and not crowd.avatars[labelled].adapted


@pytest.mark.parametrize("kind", ["controlnet", "finetune"])
def test_guidance_against_the_nearest_other_label(kind):
    # ours: G(y) + (gamma - 1) (G(y) - G(y*)), y* the other label whose prediction is nearest G(y)
    m = AdaptedDenoiser(base_net(), AdaptorConfig(kind=kind, labels=["a", "b", "c"])).eval()
    assert m.guidance == "nearest"  # the default for label adaptors
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.01)
    t, x, x0 = inputs()
    y = torch.tensor([0, 2, 1])
    with torch.no_grad():
        by_label = torch.stack([m(t, x, x0, torch.full((3,), k), scale=1.0) for k in range(3)], 1)  # (B, 3, ...)
        cond = m(t, x, x0, y, scale=1.0)
        rival = []
        for i, k in enumerate(y.tolist()):
            d = {j: float((by_label[i, j] - cond[i]).square().sum()) for j in range(3) if j != k}
            rival.append(by_label[i, min(d, key=d.get)])
        rival = torch.stack(rival)
        for gamma in (1.5, 3.0):
            assert torch.allclose(m(t, x, x0, y, scale=gamma), cond + (gamma - 1) * (cond - rival), atol=1e-5)
        # one label has no others: guidance falls back to the null control
        one = AdaptedDenoiser(base_net(), AdaptorConfig(kind=kind, labels=["a"])).eval()
        for p in one.parameters():
            p.add_(0.01)
        y1 = torch.zeros(3, dtype=torch.long)
        null = one(t, x, x0, y1, scale=1.0, drop=torch.ones(3, dtype=torch.bool))
        c1 = one(t, x, x0, y1, scale=1.0)
        assert torch.allclose(one(t, x, x0, y1, scale=2.0), c1 + (c1 - null), atol=1e-5)
    m.guidance = "others"
    with pytest.raises(ValueError, match="'nearest' or 'null'"):
        m(t, x, x0, y, scale=2.0)


def test_adapt_resumes_exactly_from_its_saved_state(tmp_path):
    """A run stopped after 4 of 6 steps and started again with the same out folder ends with the
    weights of a run that went through, and a state folder of another adaptor is refused."""
    from avatar_motor.data.cache import import_motion
    from avatar_motor.model.checkpoint import load_checkpoint
    from avatar_motor.train.adapt import AdaptConfig, adapt
    from .conftest_models import tiny_motor
    from .fixture_tools import FIXTURES
    tiny_motor(tmp_path)
    src = tmp_path / "clips"
    src.mkdir()
    for k, name in enumerate(("walk_lafan1", "walk_cmu")):
        (src / f"dataset-9_walk_normal_00{k}.bvh").write_bytes((FIXTURES / f"{name}.bvh").read_bytes())
    import_motion(src, name="clips", progress=False, workers=1)

    def cfg(out, **kw):
        return AdaptConfig(**{"task": "reach", "base": str(tmp_path / "tiny"), "data": ["clips"], "steps": 6, "batch": 4,
                              "split": "all", "swap_neighbours": 2, "swap_pool": 50, "checkpoint_every": 2,
                              "out": str(tmp_path / out), **kw})

    base = load_checkpoint(tmp_path / "tiny").net
    whole = load_adaptor(adapt(cfg("whole"), progress=False), base).adaptor_state()
    adapt(cfg("parts", steps=4), progress=False)
    assert json.loads((tmp_path / "parts" / "train_state" / "state.json").read_text())["step"] == 4
    resumed_path = adapt(cfg("parts"), progress=False)
    resumed = load_adaptor(resumed_path, base).adaptor_state()
    assert json.loads((resumed_path / "adaptor.json").read_text())["steps"] == 6
    assert whole.keys() == resumed.keys()
    for k in whole:
        assert torch.equal(whole[k], resumed[k]), k
    # the same out folder for an adaptor of another kind: named, nothing overwritten
    before = (tmp_path / "parts" / "train_state" / "state.safetensors").read_bytes()
    with pytest.raises(ValueError, match="another adaptor run.*kind"):
        adapt(cfg("parts", kind="omni"), progress=False)
    assert (tmp_path / "parts" / "train_state" / "state.safetensors").read_bytes() == before


def test_an_adaptor_carries_the_scale_its_avatars_get_by_default(tmp_path):
    """adaptor.json's scale (set by `ship --scale`) is what a label or target without a scale
    gets, in the runtime, the server and the welcome message; a broken value is named."""
    from avatar_motor.model.adaptor import ship_adaptor
    from avatar_motor.runtime.crowd import Crowd
    from avatar_motor.serve.world import World
    from .conftest_models import tiny_motor
    motor = tiny_motor(tmp_path)
    m = AdaptedDenoiser(motor.net, AdaptorConfig(control="target")).eval()
    save_adaptor(tmp_path / "trained", m, motor.name)
    assert load_adaptor(tmp_path / "trained", motor.net).default_scale == 1.0  # as trained
    ship_adaptor(tmp_path / "trained", tmp_path / "shipped", motor, "card", scale=2.5)
    ad = load_adaptor(tmp_path / "shipped", motor.net)
    assert ad.default_scale == 2.5
    crowd = Crowd(motor, seed=0, adaptors=[ad])
    i = crowd.spawn()
    crowd.set_target(i, (1.0, 2.0))
    assert crowd.avatars[i].control_scale == 2.5
    crowd.set_target(i, (1.0, 2.0), 0.5)  # a scale given is kept
    assert crowd.avatars[i].control_scale == 0.5
    world = World(motor, adaptors=[ad])
    j = world.apply({"type": "spawn"})["avatar"]
    world.apply({"type": "target", "avatar": j, "position": [2.0, 1.0]})
    assert world.crowd.avatars[j].control_scale == 2.5
    meta = json.loads((tmp_path / "shipped" / "adaptor.json").read_text())
    for bad in (-1, 11, "strong", None):
        meta["scale"] = bad
        (tmp_path / "shipped" / "adaptor.json").write_text(json.dumps(meta))
        with pytest.raises(ValueError, match="scale must be a number"):
            load_adaptor(tmp_path / "shipped", motor.net)
