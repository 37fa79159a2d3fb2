extends SceneTree
# A headless check of the add-on against a live server (tests/test_godot.py runs it with
# `godot3-server --path engines/godot -s res://tests/smoke.gd`, the server's address in
# AVATAR_MOTOR_URL): connect, spawn an avatar, pose an AvatarMotorSkeleton from the stream, check
# that Godot's FK of the streamed rotations lands on the streamed positions (the one body), that
# the wrist moves, and that a goal and an impulse are acknowledged. Prints one line
# "RESULT {json}" and quits with 0 when every check passed.

const Client = preload("res://addons/avatar_motor/avatar_motor_client.gd")
const MotorSkeleton = preload("res://addons/avatar_motor/avatar_motor_skeleton.gd")
const WRIST := 21  # right_wrist

var client
var skeleton
var started := 0
var spawn_id := ""
var commands := []
var avatar := -1
var posed := 0
var first_wrist = null
var moved := 0.0
var worst := 0.0


func _initialize():
	Engine.target_fps = 60  # headless, the main loop would otherwise spin a core
	client = Client.new()
	var url := OS.get_environment("AVATAR_MOTOR_URL")
	if url != "":
		client.url = url
	client.connect("welcomed", self, "_on_welcome")
	client.connect("frame_received", self, "_on_frame")
	root.add_child(client)
	started = OS.get_ticks_msec()


func _on_welcome(_welcome):
	spawn_id = client.spawn(Vector2(3, 0))


func _on_frame(_index):
	# after every handler of this frame (the skeleton's pose among them): signal order is not
	# connection order in Godot 3
	call_deferred("_check")


func _check():
	if skeleton == null or not skeleton.built or not client.avatars.has(avatar):
		return
	posed += 1
	var positions: PoolVector3Array = client.avatars[avatar]["positions"]
	for j in range(positions.size()):
		worst = max(worst, skeleton.joint_position(j).distance_to(positions[j]))
	var wrist: Vector3 = skeleton.joint_position(WRIST)
	if first_wrist == null:
		first_wrist = wrist
	moved = max(moved, wrist.distance_to(first_wrist))
	if posed == 20:  # steer it and kick: both must be acknowledged
		commands.append(client.goal(avatar, Vector2(0, 1.2)))
		commands.append(client.impulse(avatar, "left_kick"))


func _idle(_delta):
	if OS.get_ticks_msec() - started > 60000:
		return _finish("timed out")
	if avatar < 0 and client.replies.has(spawn_id):
		var reply: Dictionary = client.replies[spawn_id]
		if not reply.get("ok", false):
			return _finish("spawn refused: %s" % reply)
		avatar = int(reply["avatar"])
		skeleton = MotorSkeleton.new()
		skeleton.client = client
		skeleton.avatar_id = avatar
		root.add_child(skeleton)
	if posed >= 60 and commands.size() == 2:
		for id in commands:
			if not client.replies.has(id):
				return false  # waiting for the replies
		return _finish("")
	return false


func _finish(problem: String) -> bool:
	var acks := []
	for id in commands:
		acks.append(client.replies.get(id, {}).get("ok", false))
	var result := {"frames_posed": posed, "bones": skeleton.get_bone_count() if skeleton != null else 0,
				   "fk_max_error_m": worst, "wrist_moved_m": moved, "acks": acks, "problem": problem,
				   "avatar": avatar, "model": client.welcome.get("model", "")}
	var ok: bool = problem == "" and posed >= 60 and worst < 1e-3 and moved > 0.05 and acks == [true, true]
	print("RESULT " + JSON.print(result))
	quit(0 if ok else 1)
	return true
