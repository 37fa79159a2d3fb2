extends Node
class_name AvatarMotorClient
# The avatar-motor streaming protocol, version 1 (docs/protocol.md), for Godot 3: connects to
# `avatar-motor serve`, keeps the newest frame of every avatar and sends commands.
#
# Axes: the protocol's world is Godot's (Y up, right-handed, metres, an avatar at rest facing
# +Z), and its quaternions come as (x, y, z, w), Godot's Quat order: positions and rotations are
# used as they arrive, with no axis mapping.

signal welcomed(welcome)  # the server's welcome: joint names, parents, presets, adaptors, limits
signal frame_received(index)  # a new frame is in `avatars`
signal replied(reply)  # every ack or error; `replies[id]` keeps the newest per command id
signal closed()

const MAGIC := "AMF1"

export var url := "ws://127.0.0.1:8765/ws"
export var token := ""  # for a server started with --token
export var auto_open := true

var welcome := {}
var frame := -1
# avatar id -> {"positions": PoolVector3Array (22, world metres), "rotations": Array of 22 Quat:
# the pelvis's global rotation, then each joint's rotation relative to its parent}
var avatars := {}
var replies := {}

var _ws := WebSocketClient.new()
var _next_id := 1


func _ready():
	_ws.connect("connection_closed", self, "_on_closed")
	_ws.connect("connection_error", self, "_on_error")
	_ws.connect("data_received", self, "_on_data")
	if auto_open:
		open()


func open() -> int:
	var address := url
	if token != "":
		address += "?token=" + token.percent_encode()
	var err := _ws.connect_to_url(address)
	if err != OK:
		push_error("avatar-motor: cannot connect to %s (error %d): is `avatar-motor serve` running there?" % [url, err])
	return err


func close() -> void:
	_ws.disconnect_from_host()


func is_open() -> bool:
	return _ws.get_connection_status() == NetworkedMultiplayerPeer.CONNECTION_CONNECTED


func _process(_delta):
	if _ws.get_connection_status() != NetworkedMultiplayerPeer.CONNECTION_DISCONNECTED:
		_ws.poll()


# ------------------------------------------------------------------ commands
# Each returns the command's id; its reply (ack or error) arrives as `replied` and in replies[id].

func send(command: Dictionary) -> String:
	var id := "godot-%d" % _next_id
	_next_id += 1
	command["id"] = id
	var peer := _ws.get_peer(1)
	peer.set_write_mode(WebSocketPeer.WRITE_MODE_TEXT)
	var err := peer.put_packet(JSON.print(command).to_utf8())
	if err != OK:
		push_error("avatar-motor: could not send %s (error %d)" % [command.get("type"), err])
	return id


func spawn(position := Vector2.ZERO, yaw := 0.0) -> String:
	# position: world (x, z); the ack carries "avatar", the new id
	return send({"type": "spawn", "position": [position.x, position.y], "yaw": yaw})


func remove(avatar: int) -> String:
	return send({"type": "remove", "avatar": avatar})


func goal(avatar: int, velocity = null, facing = null) -> String:
	# velocity: Vector2 (x, z) m/s, or null to release; facing: Vector2 (x, z), default along it
	var command := {"type": "goal", "avatar": avatar, "velocity": null}
	if typeof(velocity) == TYPE_VECTOR2:
		command["velocity"] = [velocity.x, velocity.y]
	if typeof(facing) == TYPE_VECTOR2:
		command["facing"] = [facing.x, facing.y]
	return send(command)


func push(avatar: int, joint, velocity: Vector3, in_frame := "world") -> String:
	# joint: a name of welcome.joint_names or its index; velocity m/s added to that joint
	return send({"type": "push", "avatar": avatar, "joint": joint, "velocity": [velocity.x, velocity.y, velocity.z],
				 "frame": in_frame})


func impulse(avatar: int, preset: String, scale := 1.0) -> String:
	# preset: one of welcome.presets (left_kick, right_kick, forward_run, back_flip, forward_roll)
	return send({"type": "impulse", "avatar": avatar, "preset": preset, "scale": scale})


func target(avatar: int, position = null) -> String:
	# the magnet: world (x, z) as a Vector2, or null to release
	var command := {"type": "target", "avatar": avatar, "position": null}
	if typeof(position) == TYPE_VECTOR2:
		command["position"] = [position.x, position.y]
	return send(command)


func label(avatar: int, name, scale := 1.0) -> String:
	# an action or style of a served adaptor (welcome.adaptors), or null to release
	return send({"type": "label", "avatar": avatar, "label": name, "scale": scale})


func reset(avatar := -1) -> String:
	return send({"type": "reset"} if avatar < 0 else {"type": "reset", "avatar": avatar})


# ------------------------------------------------------------------ what arrives

func _on_data():
	var peer := _ws.get_peer(1)
	while peer.get_available_packet_count() > 0:
		var packet := peer.get_packet()
		if peer.was_string_packet():
			_on_text(packet.get_string_from_utf8())
		else:
			_on_binary(packet)


func _on_text(text: String):
	var parsed := JSON.parse(text)
	if parsed.error != OK or typeof(parsed.result) != TYPE_DICTIONARY:
		push_warning("avatar-motor: unreadable message from the server: %s" % text.substr(0, 200))
		return
	var message: Dictionary = parsed.result
	match message.get("type", ""):
		"welcome":
			welcome = message
			emit_signal("welcomed", message)
		"ack", "error":
			if message.get("id") != null:
				replies[str(message["id"])] = message
			if message["type"] == "error":
				push_warning("avatar-motor: %s" % message.get("error"))
			emit_signal("replied", message)
		"frame":
			_on_json_frame(message)


func _on_binary(data: PoolByteArray):
	# docs/protocol.md "Frames": magic, frame index, avatar count, joint count, then per avatar its
	# id, 3 x joints float32 positions and 4 x joints float32 rotations (x, y, z, w), little-endian
	if data.size() < 12 or data.subarray(0, 3).get_string_from_ascii() != MAGIC:
		push_warning("avatar-motor: a binary message that is not a frame (%d bytes)" % data.size())
		return
	var buffer := StreamPeerBuffer.new()
	buffer.data_array = data
	buffer.big_endian = false
	buffer.seek(4)
	var index := buffer.get_u32()
	var count := buffer.get_u16()
	var joints := buffer.get_u16()
	if data.size() != 12 + count * (4 + joints * 28):
		push_warning("avatar-motor: a frame of %d bytes for %d avatars of %d joints" % [data.size(), count, joints])
		return
	var now := {}
	for _k in range(count):
		var id := buffer.get_u32()
		var positions := PoolVector3Array()
		for _j in range(joints):
			var x := buffer.get_float()
			var y := buffer.get_float()
			var z := buffer.get_float()
			positions.append(Vector3(x, y, z))
		var rotations := []
		for _j in range(joints):
			var qx := buffer.get_float()
			var qy := buffer.get_float()
			var qz := buffer.get_float()
			var qw := buffer.get_float()
			rotations.append(Quat(qx, qy, qz, qw))
		now[id] = {"positions": positions, "rotations": rotations}
	avatars = now
	frame = index
	emit_signal("frame_received", index)


func _on_json_frame(message: Dictionary):
	var now := {}
	for avatar in message.get("avatars", []):
		var positions := PoolVector3Array()
		for p in avatar["positions"]:
			positions.append(Vector3(p[0], p[1], p[2]))
		var rotations := []
		for q in avatar["rotations"]:
			rotations.append(Quat(q[0], q[1], q[2], q[3]))
		now[int(avatar["id"])] = {"positions": positions, "rotations": rotations}
	avatars = now
	frame = int(message["frame"])
	emit_signal("frame_received", frame)


func _on_closed(_clean := false):
	emit_signal("closed")


func _on_error():
	push_error("avatar-motor: the connection to %s failed: is `avatar-motor serve` running there?" % url)
	emit_signal("closed")
