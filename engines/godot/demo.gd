extends Spatial
# The add-on's demo: every avatar of the world a server streams, as a skeleton with a sphere on
# each joint. WASD walks avatar 0 (Shift runs), 1-5 fire the impulse presets, P pushes its head,
# N spawns one more. Start `avatar-motor serve` first, then run this scene (F5 in the editor).

const SPEED := 1.2
const RUN := 3.0

onready var client = $AvatarMotorClient
var skeletons := {}
var walking := Vector2.ZERO


func _ready():
	client.connect("frame_received", self, "_on_frame")


func _on_frame(_index):
	for id in client.avatars:
		if not skeletons.has(id):  # a skeleton for each avatar that appears
			var skeleton = preload("res://addons/avatar_motor/avatar_motor_skeleton.gd").new()
			skeleton.client = client
			skeleton.avatar_id = id
			add_child(skeleton)
			skeletons[id] = skeleton
	for id in skeletons.keys():
		if not client.avatars.has(id):  # removed on the server
			skeletons[id].queue_free()
			skeletons.erase(id)


func _process(_delta):
	var want := Vector2(
		float(Input.is_key_pressed(KEY_D)) - float(Input.is_key_pressed(KEY_A)),
		float(Input.is_key_pressed(KEY_S)) - float(Input.is_key_pressed(KEY_W)))
	if want.length() > 0:
		want = want.normalized() * (RUN if Input.is_key_pressed(KEY_SHIFT) else SPEED)
	if want != walking and client.is_open():  # only changes are sent: the server coalesces the rest
		walking = want
		client.goal(0, want if want.length() > 0 else null)


func _unhandled_key_input(event):
	if not event.pressed or event.echo or not client.is_open():
		return
	var presets := {KEY_1: "left_kick", KEY_2: "right_kick", KEY_3: "forward_run", KEY_4: "back_flip", KEY_5: "forward_roll"}
	if presets.has(event.scancode):
		client.impulse(0, presets[event.scancode])
	elif event.scancode == KEY_P:
		client.push(0, "head", Vector3(0, 0, -3))
	elif event.scancode == KEY_N:
		client.spawn(Vector2(randf() * 4 - 2, randf() * 4 - 2))
