import math

import pytest
import torch

from avatar_motor.body import rotations as rot
from avatar_motor.body.motion_state import SLICES, STATE_DIM
from avatar_motor.body.skeleton import SHAPE_DIM
from avatar_motor.model.denoiser import Denoiser, DenoiserConfig
from avatar_motor.model.persona import TEXT_DIM, PersonaCond, trajectory_of

from .test_model import TINY, _cfg, fixture_cache  # noqa: F401  (the fixture is used by name)

PTINY = DenoiserConfig(**{**TINY.to_dict(), "persona": True})


def _inputs(B=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randint(50, (B,), generator=g), torch.randn(B, 15, STATE_DIM, generator=g),
            torch.randn(B, STATE_DIM, generator=g), g)


def _cond(B, g, present=True):
    c = PersonaCond(torch.randn(B, TEXT_DIM, generator=g), torch.randn(B, SHAPE_DIM, generator=g),
                    torch.randn(B, 15, 4, generator=g), torch.ones(B, 3, dtype=torch.bool))
    if not present:
        c.present[:] = False
    return c


def _randomize(net):
    """Persona embedders with a random, not negligible effect (they start at zero: the base)."""
    g = torch.Generator().manual_seed(1)
    for p in net.persona.parameters():
        p.data = torch.randn(p.shape, generator=g) * 0.3


def test_a_persona_network_starts_as_its_base_and_absent_conditions_add_nothing():
    torch.manual_seed(0)
    base = Denoiser(TINY).eval()
    net = Denoiser(PTINY).eval()
    missing, unexpected = net.load_state_dict(base.state_dict(), strict=False)
    assert not unexpected and missing and all(k.startswith("persona.") for k in missing)
    t, x, x0, g = _inputs()
    ref = base(t, x, x0)
    assert torch.equal(net(t, x, x0), ref)
    c = _cond(4, g)
    assert torch.equal(net(t, x, x0, persona=c), ref)  # zero-initialised: the start is the base, conditions or not
    _randomize(net)
    assert torch.equal(net(t, x, x0, persona=_cond(4, g, present=False)), ref)  # absent: nothing added
    for which in ("text", "shape", "trajectory"):  # each present condition changes the output...
        only = PersonaCond(c.text, c.shape, c.trajectory, torch.zeros(4, 3, dtype=torch.bool))
        only.present[:, ["text", "shape", "trajectory"].index(which)] = True
        assert not torch.allclose(net(t, x, x0, persona=only), ref, atol=1e-3), which
    # ...and an absent one's values do not matter
    no_text = c.without("text")
    other = PersonaCond(torch.randn(4, TEXT_DIM), c.shape, c.trajectory, no_text.present)
    assert torch.equal(net(t, x, x0, persona=no_text), net(t, x, x0, persona=other))
    # rows are independent: a row's output does not depend on another row's conditions
    mixed = PersonaCond.cat([c.select(slice(0, 2)), no_text.select(slice(2, 4))])
    assert torch.allclose(net(t, x, x0, persona=mixed)[:2], net(t, x, x0, persona=c)[:2], atol=1e-5)


def test_persona_config_is_checked():
    with pytest.raises(ValueError, match="blend"):
        DenoiserConfig.from_dict({"blend": 16})
    with pytest.raises(ValueError, match="persona"):
        DenoiserConfig.from_dict({"persona": 1})


def test_in_diffusion_blending_pulls_the_first_frames_to_the_initial_state():
    net = Denoiser(DenoiserConfig(**{**TINY.to_dict(), "blend": 5}))
    _, x, x0, _ = _inputs()
    b = net.blended(x, x0)
    assert torch.allclose(b[:, 0], x0, atol=1e-6)  # weight 1 on the first frame
    assert torch.allclose(b[:, 2], 0.6 * x0 + 0.4 * x[:, 2], atol=1e-6)  # linear from 1 to 0 over 5 frames
    assert torch.equal(b[:, 5:], x[:, 5:])


def test_trajectory_is_the_roots_ground_path_and_facing():
    x = torch.zeros(1, 3, STATE_DIM)
    yaw = torch.tensor([0.0, math.pi / 2, -math.pi / 4])
    R = rot.axis_angle_to_matrix(torch.stack((torch.zeros(3), yaw, torch.zeros(3)), -1))
    x[0, :, SLICES["root_rot"]] = rot.matrix_to_6d(R)
    x[0, :, SLICES["root_pos"]] = torch.tensor([[0.0, 0.9, 0.0], [0.1, 0.95, 0.5], [-0.2, 0.9, 1.0]])
    tr = trajectory_of(x)[0]
    assert torch.allclose(tr[:, :2], torch.tensor([[0.0, 0.0], [0.1, 0.5], [-0.2, 1.0]]))
    assert torch.allclose(tr[:, 2], torch.sin(yaw), atol=1e-6) and torch.allclose(tr[:, 3], torch.cos(yaw), atol=1e-6)


def test_text_embeddings_place_paraphrases_together_and_refuse_bad_text():
    from avatar_motor.model.text import embed_texts
    e = embed_texts(["a weary old man", "an elderly man, slow and a little frail", "an energetic teenager"])
    assert e.shape == (3, TEXT_DIM) and torch.allclose(e.norm(dim=1), torch.ones(3), atol=1e-5)
    assert float(e[0] @ e[1]) > float(e[0] @ e[2]) + 0.2
    for bad in ("", "   ", "x" * 501, None):
        with pytest.raises(ValueError, match="persona description"):
            embed_texts([bad])


def test_every_style_has_training_and_held_out_descriptions():
    from avatar_motor.data.personas import DESCRIPTIONS, TRAIN, descriptions
    bandai = {"active", "elderly", "exhausted", "feminine", "masculine", "normal", "youthful", "happy", "sad", "angry",
              "proud", "not-confident", "masculinity", "childish", "old", "tired", "musical", "giant", "chimpira"}
    assert bandai <= set(DESCRIPTIONS)
    every = [s for lab in DESCRIPTIONS for s in descriptions(lab, "all")]
    assert len(every) == len(set(every))  # no sentence stands for two labels
    for lab in DESCRIPTIONS:
        assert len(descriptions(lab)) == TRAIN and len(descriptions(lab, "heldout")) >= 2


def test_a_persona_run_starts_from_a_plain_base_and_trains_its_tokens(tmp_path, fixture_cache):  # noqa: F811
    from avatar_motor.model.checkpoint import load_checkpoint
    from avatar_motor.train.trainer import PersonaTexts, Trainer
    Trainer(_cfg(tmp_path / "base", fixture_cache, steps=2), progress=False).run()
    base = load_checkpoint(tmp_path / "base" / "checkpoint").net.eval()
    tr = Trainer(_cfg(tmp_path / "p", fixture_cache, steps=3, init=str(tmp_path / "base" / "checkpoint"),
                      model=PTINY, persona_dropout=0.0), progress=False)
    t, x, x0, _ = _inputs()
    tr.net.eval()
    assert torch.equal(tr.net(t, x, x0), base(t, x, x0))  # the start is the base
    # the fixtures carry no style: give the clips Bandai labels so that the text is drawn
    tr.ds.clip_labels = [{"style": "elderly" if i % 2 else "youthful"} for i in range(len(tr.ds.clip_labels))]
    tr.texts = PersonaTexts(tr.ds)
    xs, shapes, clip = tr.ds.sample_indexed(8, torch.Generator().manual_seed(1))
    c = tr.persona_batch(xs, shapes, clip)
    assert bool(c.present.all()) and torch.equal(c.shape, shapes)
    assert torch.allclose(c.trajectory, trajectory_of(xs[:, 1:]))
    tr.run()
    for name in ("text", "shape", "trajectory"):  # every condition's embedder learned (from zero)
        assert float(getattr(tr.net.persona, name)[2].weight.detach().abs().max()) > 0, name
    ck = load_checkpoint(tmp_path / "p" / "checkpoint")
    assert ck.net.cfg.persona
    with pytest.raises(ValueError, match="same architecture"):  # a persona network is no init for a plain one
        Trainer(_cfg(tmp_path / "q", fixture_cache, init=str(tmp_path / "p" / "checkpoint")), progress=False)


def _persona_motor(tmp_path, seed=0):
    from avatar_motor.data.dataset import Normalizer
    from avatar_motor.model.checkpoint import load_checkpoint, save_checkpoint
    torch.manual_seed(seed)
    net = Denoiser(PTINY)
    _randomize(net)
    save_checkpoint(tmp_path / "ptiny", net, Normalizer(torch.zeros(STATE_DIM), torch.full((STATE_DIM,), 0.05)),
                    {"name": "ptiny", "licence": "test only"})
    return load_checkpoint(tmp_path / "ptiny")


def test_goal_trajectory_starts_from_the_body_and_approaches_the_goal():
    from avatar_motor.body.motion_state import FPS
    from avatar_motor.runtime.crowd import standing_state
    from avatar_motor.runtime.guidance import goal_trajectory
    x0 = standing_state()[None].double()  # canonical already: at the origin, facing +Z, at rest
    v = torch.tensor([[0.0, 0.0, 1.2]], dtype=torch.float64)
    tr = goal_trajectory(x0, v, None, 90)[0]
    step = (tr[1:, :2] - tr[:-1, :2]).norm(dim=-1) * FPS
    assert float(step[0]) < 0.4 and abs(float(step[-1]) - 1.2) < 0.01  # speeds up from rest to the goal
    assert torch.all(step[1:] >= step[:-1] - 1e-9) and torch.allclose(tr[:, 0], torch.zeros(90, dtype=torch.float64))
    assert torch.allclose(tr[:, 3], torch.ones(90, dtype=torch.float64))  # no facing goal: keeps facing +Z
    # a facing goal to the body's left (+X) turns it the short way, by about half in one halflife
    tr = goal_trajectory(x0, v * 0, torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64), 90, halflife=0.5)[0]
    yaw = torch.atan2(tr[:, 2], tr[:, 3])
    assert abs(float(yaw[14]) - math.pi / 4) < 0.02 and abs(float(yaw[-1]) - math.pi / 2) < 0.1
    assert torch.allclose(tr[:, :2], torch.zeros(90, 2, dtype=torch.float64))  # no velocity: stays


def test_avatars_with_personas_move_differently_and_the_rest_as_without(tmp_path):
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    motor = _persona_motor(tmp_path)
    cfg = RuntimeConfig(steps=2)

    def run(personas, goal=None):
        crowd = Crowd(motor, cfg, seed=3)
        ids = [crowd.spawn(position=(2.0 * k, 0.0)) for k in range(len(personas))]
        for i, p in zip(ids, personas):
            crowd.set_persona(i, p)
            if goal is not None:
                crowd.set_goal(i, goal)
        seg = crowd.step_segment()
        return torch.stack([seg[i] for i in ids])

    plain = run([None, None])
    mixed = run([None, "a weary old man"])
    assert torch.allclose(mixed[0], plain[0], atol=1e-5)  # another avatar's persona changes nothing
    assert not torch.allclose(mixed[1], plain[1], atol=1e-3)
    other = run([None, "an energetic teenager"])
    assert not torch.allclose(other[1], mixed[1], atol=1e-3)  # the words matter
    steered = run([None, "a weary old man"], goal=(0.0, 1.2))
    assert not torch.allclose(steered[1], mixed[1], atol=1e-3)  # and the trajectory
    crowd = Crowd(motor, cfg)
    i = crowd.spawn()
    with pytest.raises(ValueError, match="persona description"):
        crowd.set_persona(i, "")


def test_a_plain_model_refuses_a_persona_by_name(tmp_path):
    from avatar_motor.runtime.crowd import Crowd
    from .conftest_models import tiny_motor
    crowd = Crowd(tiny_motor(tmp_path))
    with pytest.raises(ValueError, match="no persona conditions"):
        crowd.set_persona(crowd.spawn(), "a weary old man")


def test_eval_control_steers_characters_and_refuses_them_on_a_plain_model(tmp_path):
    """eval control --persona: the rollouts' avatars take the descriptions in turn; the steered
    rows differ from the same goals without a character; a plain model is refused by name."""
    from avatar_motor.eval.control import control
    from .conftest_models import tiny_motor
    motor = _persona_motor(tmp_path)
    plain_rows, _, _ = control(motor, None, n=2, seconds=1.2)
    rows, _, body = control(motor, None, n=2, seconds=1.2, personas=["a weary old man", "an energetic teenager"])
    assert len(rows) == len(plain_rows) == 9 and all(math.isfinite(r["vel_err"]) for r in rows[1:])
    assert any(abs(a["vel_err"] - b["vel_err"]) > 1e-6 for a, b in zip(rows[1:], plain_rows[1:]))
    with pytest.raises(ValueError, match="no persona condition"):
        control(tiny_motor(tmp_path), None, n=2, seconds=1.2, personas=["a weary old man"])


def test_frechet_distance_and_diversity_on_known_gaussians():
    from avatar_motor.eval.persona import diversity, frechet
    g = torch.Generator().manual_seed(0)
    a = torch.randn(20000, 3, generator=g, dtype=torch.float64)
    b = torch.randn(20000, 3, generator=g, dtype=torch.float64) * 2 + torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    # N(0, I) against N((1, 0, 0), 4 I): 1 + 3 (1 + 4 - 2 * 2) = 4
    assert abs(frechet(a, b) - 4.0) < 0.1 and abs(frechet(a, a)) < 1e-9
    assert abs(frechet(a, b) - frechet(b, a)) < 1e-6
    pts = torch.tensor([[0.0, 0.0], [3.0, 0.0], [0.0, 4.0]], dtype=torch.float64)
    assert abs(diversity(pts) - (3 + 4 + 5) / 3) < 1e-12  # the mean over the pairs, each once


def test_trajectory_errors_and_foot_sliding_on_made_up_motion():
    from avatar_motor.body.motion_state import SLICES as S
    from avatar_motor.eval.persona import fsd, trajectory_errors
    from avatar_motor.runtime.crowd import standing_state
    from avatar_motor.runtime.guidance import goal_trajectory
    x0 = standing_state().double()
    goal = torch.tensor([[0.0, 0.0, 1.0]])
    path = goal_trajectory(x0[None], goal.double(), goal.double(), 60)[0]  # canonical = world here
    X = x0.repeat(61, 1)
    for f in range(1, 61):  # the body carried rigidly along the commanded path
        d = torch.tensor([path[f - 1, 0], 0.0, path[f - 1, 1]], dtype=torch.float64)
        X[f, S["joints"]] = (x0[S["joints"]].view(22, 3) + d).flatten()
        X[f, S["root_pos"]] = x0[S["root_pos"]] + d
    tpe, tde = trajectory_errors(X[None], goal)
    assert tpe < 1e-6 and tde < 1e-3
    side = X.clone()
    side[1:, S["joints"]] += torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64).repeat(22)
    assert abs(trajectory_errors(side[None], goal)[0] - 0.1) < 1e-6
    J = X[:, S["joints"]].view(1, 61, 22, 3).float()
    assert fsd(J) > 1.0  # feet carried along the ground slide (cm per frame)
    assert fsd(J[:, :1].repeat(1, 30, 1, 1)) == 0.0  # planted feet do not


def test_the_persona_command_is_validated_and_carried_out(tmp_path):
    from avatar_motor.runtime.crowd import RuntimeConfig
    from avatar_motor.serve.protocol import ProtocolError, parse_message
    from avatar_motor.serve.world import CommandError, World
    from .conftest_models import tiny_motor
    cmd = parse_message('{"type": "persona", "avatar": 0, "description": "a weary old man"}')
    assert cmd == {"type": "persona", "avatar": 0, "description": "a weary old man"}
    assert parse_message('{"type": "persona", "avatar": 0, "description": null}')["description"] is None
    for bad in ('"   "', '"' + "x" * 301 + '"', "7", "[]"):
        with pytest.raises(ProtocolError, match="description"):
            parse_message('{"type": "persona", "avatar": 0, "description": %s}' % bad)
    world = World(_persona_motor(tmp_path), RuntimeConfig(steps=2))
    world.apply({"type": "spawn"})
    world.apply(cmd)
    assert world.crowd.avatars[0].persona == "a weary old man"
    world.apply({"type": "persona", "avatar": 0, "description": None})
    assert world.crowd.avatars[0].persona is None
    plain = World(tiny_motor(tmp_path))
    plain.apply({"type": "spawn"})
    with pytest.raises(CommandError, match="no persona conditions"):
        plain.apply(cmd)


def test_strides_are_the_distances_between_plants_of_one_foot():
    from avatar_motor.body.skeleton import JOINT_INDEX
    from avatar_motor.eval.persona import strides
    T = 90
    J = torch.zeros(T, 22, 3)
    J[..., 1] = 0.5  # every joint in the air...
    for j, phase in ((JOINT_INDEX["left_foot"], 0), (JOINT_INDEX["right_foot"], 15)):
        for t in range(T):
            k, r = divmod(t + phase, 30)  # ...but the feet: planted 15 frames, 15 swinging, 1.4 m a stride
            J[t, j] = torch.tensor([0.0, 0.02, 1.4 * k]) if r < 15 else torch.tensor([0.0, 0.3, 1.4 * k + 1.4 * (r - 14) / 16])
    s = strides(J)
    assert len(s) >= 4 and all(abs(v - 1.4) < 1e-5 for v in s), s


def test_text_guidance_strengthens_the_text_and_leaves_the_rest(tmp_path):
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    motor = _persona_motor(tmp_path)

    def run(scale):
        crowd = Crowd(motor, RuntimeConfig(steps=2, persona_scale=scale), seed=3)
        ids = [crowd.spawn(position=(2.0 * k, 0.0)) for k in range(2)]
        crowd.set_persona(ids[1], "a weary old man")
        seg = crowd.step_segment()
        return [seg[i] for i in ids]
    one, two = run(1.0), run(2.5)
    assert torch.allclose(one[0], two[0], atol=1e-4, rtol=1e-4)  # no text: nothing to guide (float noise)
    assert float((one[1] - two[1]).abs().max()) > 0.01


def test_trajectory_guidance_strengthens_the_path_of_steered_avatars_only(tmp_path):
    """trajectory_scale guides against the same conditions without the trajectory: an avatar with
    no goal has none and comes out as without guidance; with text guidance too, each guidance
    is its own term (c + sum (w_k - 1)(c - u_k)), so a text scale of 1 adds nothing to it."""
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    motor = _persona_motor(tmp_path)

    def run(**kw):
        crowd = Crowd(motor, RuntimeConfig(steps=2, bfloat16_from=0, **kw), seed=3)  # one precision whatever the rows
        ids = [crowd.spawn(position=(2.0 * k, 0.0)) for k in range(3)]
        crowd.set_persona(ids[2], "a weary old man")
        crowd.set_goal(ids[1], (0.0, 1.2))
        crowd.set_goal(ids[2], (1.0, 0.0))
        seg = crowd.step_segment()
        return [seg[i] for i in ids]
    one, guided = run(), run(trajectory_scale=3.0)
    assert torch.allclose(one[0], guided[0], atol=1e-4, rtol=1e-4)  # no goal: no trajectory to guide
    assert float((one[1] - guided[1]).abs().max()) > 0.01
    both = run(trajectory_scale=3.0, persona_scale=2.0)
    assert torch.allclose(both[1], guided[1], atol=1e-4, rtol=1e-4)  # no text: the text term is nothing
    assert float((both[2] - guided[2]).abs().max()) > 0.01
    assert float((run(trajectory_halflife=0.25)[1] - one[1]).abs().max()) > 0.01  # the path asked for changed
    with pytest.raises(ValueError, match="trajectory_halflife"):  # at once, not at the first steered segment
        Crowd(motor, RuntimeConfig(trajectory_halflife=0.0))
    with pytest.raises(ValueError, match="trajectory_scale"):
        Crowd(motor, RuntimeConfig(trajectory_scale=float("nan")))


def test_characterization_continues_the_clip_from_feet_matched_states(tmp_path):
    """swap_partners: each clip window's partners are the other motion's windows whose initial
    ankles and feet are nearest (the rest of the state does not count); prior_windows gives a
    without_text share of its avatars no description (a zero text, marked absent)."""
    from avatar_motor.body.motion_state import SLICES
    from avatar_motor.body.skeleton import ANKLES_AND_FEET
    from avatar_motor.train.characterize import prior_windows, swap_partners
    src = _persona_motor(tmp_path)
    g = torch.Generator().manual_seed(0)
    starts = torch.randn(6, 3, 267, generator=g)
    clip = starts[[4, 1]].clone()
    clip[:, :, SLICES["root_pos"]] += 5.0  # far elsewhere, but the same feet
    feet = [sl.start + 3 * j + k for sl in (SLICES["joints"], SLICES["velocities"]) for j in ANKLES_AND_FEET for k in range(3)]
    clip[1, 0, feet] = starts[2, 0, feet]  # window 1's feet (where and how fast) are now those of start 2
    assert swap_partners(clip, starts, src.norm, 1)[:, 0].tolist() == [4, 2]
    assert swap_partners(clip, starts, src.norm, 3).shape == (2, 3)
    W, shapes, text, has_text = prior_windows(src, 4, 1.0, src.net.cfg.frames, 0, without_text=1.0)
    assert not bool(has_text.any()) and bool((text == 0).all()) and len(W) == len(shapes) == len(has_text)


def test_adapt_persona_characterizes_a_model_from_a_clip(tmp_path):
    from avatar_motor.cli import main
    from avatar_motor.model.checkpoint import load_checkpoint
    from avatar_motor.runtime.crowd import Crowd, RuntimeConfig
    from avatar_motor.train.characterize import identifier
    from .fixture_tools import FIXTURES
    src = _persona_motor(tmp_path)
    clip = str(FIXTURES / "walk_cmu.bvh")
    out = tmp_path / "grandpa"
    args = ["adapt", "persona", clip, "--name", "grandpa", "--model", str(src.path), "--out", str(out),
            "--set", "steps=4", "--set", "prior_avatars=2", "--set", "prior_seconds=1", "--set", "batch=8"]
    assert main(args) == 0
    m = load_checkpoint(out)
    assert m.net.cfg.persona and torch.allclose(torch.tensor(m.config["personas"]["grandpa"]), identifier("grandpa"))
    assert m.config["characterized"]["clips"] == ["walk_cmu.bvh"] and "non-commercial" in (out / "card.md").read_text()
    changed = [k for k, v in m.net.state_dict().items() if not torch.equal(v, src.net.state_dict()[k])]
    assert changed  # fine-tuned
    crowd = Crowd(m, RuntimeConfig(steps=2))
    i = crowd.spawn()
    crowd.set_persona(i, "grandpa")  # the name gives the identifier, not a sentence's embedding
    assert torch.allclose(crowd.avatars[i].persona_text, identifier("grandpa"))
    crowd.step_segment()
    # bad input: a name that is not an identifier, a missing file, a plain model
    assert main(args[:3] + ["--name", "grand pa"] + args[5:]) == 2
    assert main(["adapt", "persona", str(tmp_path / "none.bvh"), "--name", "x", "--model", str(src.path)]) == 2
    assert main(args + ["--set", "swap=1.5"]) == 2 and main(args + ["--set", "clip_share=1"]) == 2
    from .conftest_models import tiny_motor
    plain = tiny_motor(tmp_path)
    assert main(["adapt", "persona", clip, "--name", "x", "--model", str(plain.path)]) == 2


def test_the_python_api_gives_an_avatar_a_persona(tmp_path):
    import avatar_motor as am
    scene = am.Scene(am.Model(_persona_motor(tmp_path)), seed=0)
    a = scene.spawn(shape=[-0.5, -0.5, 0, 0, 0, 0])
    scene.persona(a, "a weary old man")
    scene.goal(a, velocity=(0.0, 1.0))
    scene.run(1.0)
    assert scene.crowd.avatars[a].persona == "a weary old man" and len(scene.motion(a)) > 30
    scene.persona(a, None)
    assert scene.crowd.avatars[a].persona is None


def test_persona_swap_gives_text_windows_a_feet_matched_state_of_another_style(tmp_path, fixture_cache):  # noqa: F811
    from avatar_motor.train.trainer import PersonaTexts, Trainer
    tr = Trainer(_cfg(tmp_path / "p", fixture_cache, steps=2, model=PTINY, persona_dropout=0.0, persona_swap=1.0,
                      persona_neighbours=4), progress=False)
    n = len(tr.ds.clip_labels)
    tr.ds.clip_labels = [{"style": "elderly" if i % 2 else "youthful"} for i in range(n)]
    tr.texts = PersonaTexts(tr.ds)
    tr.pool_style = tr.texts.clip_style[tr.pool.clip]
    x, shapes, clip = tr.ds.sample_indexed(8, torch.Generator().manual_seed(2))
    c = tr.persona_batch(x, shapes, clip)
    x0 = tr.swapped_initial(x, shapes, clip, c)
    moved = (x0 - x[:, 0]).abs().amax(-1) > 1e-6
    assert bool(moved.all())  # every window with a text continues from another style's state
    c.present[:4, 0] = False
    x0 = tr.swapped_initial(x, shapes, clip, c)
    assert torch.equal(x0[:4], x[:4, 0])  # without a text the window keeps its own state
    tr.run()  # and training runs with it
    with pytest.raises(ValueError, match="persona_swap"):
        Trainer(_cfg(tmp_path / "q", fixture_cache, model=PTINY, persona_swap=1.5), progress=False)


def test_join_jerk_reads_a_seam_at_the_joins_and_nothing_in_smooth_motion():
    from avatar_motor.eval.metrics import join_jerk
    t = torch.arange(91, dtype=torch.float64) / 30
    J = torch.zeros(2, 91, 22, 3, dtype=torch.float64)
    J[..., 0] = torch.sin(2 * t)[None, :, None]  # every joint swaying smoothly
    J[..., 2] = (0.5 * t ** 3)[None, :, None]  # and moving on with a constant jerk
    joins = [[1, 16, 31, 46, 61, 76]] * 2
    assert abs(join_jerk(J, joins) - 1.0) < 0.1  # seams where there are none: no different
    seamed = J.clone()
    for j in joins[0]:
        seamed[:, j:, :, 1] += 0.01  # each segment starts 1 cm off where the one before ended
    assert join_jerk(seamed, joins) > 10
    assert join_jerk(seamed, [[5, 20, 35, 50, 65, 80]] * 2) < 1.0  # read at the wrong frames: the seams count as within
    with pytest.raises(ValueError, match="both across and away"):
        join_jerk(J, [[]] * 2)


def test_eval_persona_reads_the_part_after_settling(tmp_path, monkeypatch):
    """With `settle`, the rollouts run that much longer and the evaluator reads their tail: the
    same frames as the end of a longer rollout without settling (same seed), not its start."""
    from avatar_motor.eval import persona as P
    from avatar_motor.runtime.crowd import RuntimeConfig, standing_state
    motor = _persona_motor(tmp_path)
    cfg = RuntimeConfig(steps=2)
    init = standing_state()[None].repeat(2, 1)
    shapes = torch.zeros(2, SHAPE_DIM)
    read = []
    monkeypatch.setattr(P, "top_k", lambda encoders, X, y, k: read.append(X.clone()) or 0.0)
    methods = {"persona": (motor, None, P._described("train"))}
    P.eval_persona(methods, [], init, shapes, ["elderly"], seconds=0.5, cfg=cfg, settle=0.5)
    settled = read[0]
    assert settled.shape[1] == 16  # a rollout has its initial frame and 15 more
    read.clear()
    P.eval_persona(methods, [], init, shapes, ["elderly"], seconds=1.0, cfg=cfg)
    whole = read[0]
    assert whole.shape[1] == 31
    assert torch.allclose(settled, whole[:, 15:]) and not torch.allclose(settled, whole[:, :16])
    from avatar_motor.eval.realism import rollout
    joins = []
    rollout(motor, init, shapes, 30, cfg, 0, joins_out=joins)
    assert joins == [[1, 16]] * 2  # each segment's first frame (15 frames each), after the initial state


def test_eval_persona_refuses_a_negative_settle_before_loading_anything(capsys):
    from avatar_motor.cli import main
    assert main(["eval", "persona", "--settle", "-1", "--model", "/nonexistent"]) == 2
    assert "--settle must be 0 or more" in capsys.readouterr().err


def test_prior_on_clip_body_preserves_the_clips_body_without_the_name(tmp_path, monkeypatch):
    """With prior_on_clip_body, prior-preservation windows include the model's own motion on the
    clip's body (some without a description); without it every prior window is on a random body."""
    from avatar_motor.train import characterize as C
    from .fixture_tools import FIXTURES
    src = _persona_motor(tmp_path)
    seen = []
    real_loss = C.motion_loss

    def loss(pred, target, x0, shapes, *rest):
        seen.append(shapes.clone())
        return real_loss(pred, target, x0, shapes, *rest)
    monkeypatch.setattr(C, "motion_loss", loss)
    clip = str(FIXTURES / "walk_cmu.bvh")
    _, body = C.clip_windows([clip], src.net.cfg.frames)

    def prior_rows_on_body(flag):
        seen.clear()
        cfg = C.CharacterizeConfig(model=str(src.path), clips=[clip], name="x", out=str(tmp_path / f"x{flag}"), steps=6,
                                   batch=16, prior_avatars=2, prior_seconds=1.0, prior_on_clip_body=flag)
        C.characterize(cfg, progress=lambda *_: None)
        n_clip = round(16 * cfg.clip_share)
        return sum(int(torch.isclose(s[n_clip:], body.float()).all(-1).sum()) for s in seen)
    assert prior_rows_on_body(False) == 0
    assert prior_rows_on_body(True) > 0


def test_persona_without_leaves_a_condition_out_of_every_training_window(tmp_path, fixture_cache):  # noqa: F811
    """The ablations of MotionPersona Table 5: a condition never given in training."""
    from avatar_motor.train.trainer import PersonaTexts, Trainer
    tr = Trainer(_cfg(tmp_path / "p", fixture_cache, steps=2, model=PTINY, persona_dropout=0.0,
                      persona_without=["text"]), progress=False)
    n = len(tr.ds.clip_labels)
    tr.ds.clip_labels = [{"style": "elderly"} for _ in range(n)]
    tr.texts = PersonaTexts(tr.ds)
    x, shapes, clip = tr.ds.sample_indexed(16, torch.Generator().manual_seed(2))
    c = tr.persona_batch(x, shapes, clip)
    assert not bool(c.present[:, 0].any()) and bool(c.present[:, 1:].all())  # no text; shape and path always
    with pytest.raises(ValueError, match="persona_without.*'gait'.*text"):
        Trainer(_cfg(tmp_path / "q", fixture_cache, model=PTINY, persona_without=["gait"]), progress=False)


def test_a_learnt_identifier_moves_off_its_random_start_and_stays_a_unit_vector(tmp_path):
    """identifier_lr > 0 (textual inversion): the name's vector is trained with the weights and
    saved normalised; at 0 the saved vector is the fixed random one."""
    import json
    from avatar_motor.train import characterize as C
    from .fixture_tools import FIXTURES
    src = _persona_motor(tmp_path)
    clip = str(FIXTURES / "walk_cmu.bvh")

    def saved(lr, out):
        cfg = C.CharacterizeConfig(model=str(src.path), clips=[clip], name="kid", out=str(tmp_path / out), steps=6,
                                   batch=16, prior_avatars=2, prior_seconds=1.0, identifier_lr=lr)
        C.characterize(cfg, progress=lambda *_: None)
        return torch.tensor(json.loads((tmp_path / out / "config.json").read_text())["personas"]["kid"])
    fixed, learnt = saved(0.0, "fixed"), saved(0.05, "learnt")
    start = C.identifier("kid")
    assert torch.allclose(fixed, start, atol=1e-6)
    assert abs(float(learnt.norm()) - 1.0) < 1e-5
    assert float(learnt @ start) < 0.999  # it moved
