extends Skeleton
class_name AvatarMotorSkeleton
# A Skeleton posed by one avatar of an AvatarMotorClient.
#
# The protocol's rotations are joint 0's global rotation (the pelvis) and each other joint's
# rotation relative to its parent, with every joint frame aligned with the world at rest. So the
# bones' rests are translations by the avatar's bone offsets (read once, from its first frame: the
# offset of joint j is its parent's global rotation inverted, applied to p_j - p_parent), and each
# frame sets bone j's pose to its rotation (the pelvis's also to its position). Godot's own FK then
# puts every joint where the server's positions say, to float32 precision: the one body that the
# studio draws and every export carries (tests/smoke.gd checks it).
#
# To drive a rigged character instead, retarget from this skeleton (its bones have the protocol's
# joint names), or copy the rotations onto your rig with the rest-pose correction of your rig.

export var client_path: NodePath  # an AvatarMotorClient (or set `client` before adding this node)
export var avatar_id := 0
export var draw_mannequin := true  # a sphere on every joint, for a skeleton without a mesh

var client: Node = null
var built := false


func _ready():
	if client == null:
		client = get_node(client_path)
	client.connect("frame_received", self, "_on_frame")


func _on_frame(_index):
	var avatar = client.avatars.get(avatar_id)
	if avatar == null:
		return
	if not built:
		_build(avatar)
	var rotations: Array = avatar["rotations"]
	set_bone_pose(0, Transform(Basis(rotations[0]), avatar["positions"][0]))
	for j in range(1, rotations.size()):
		set_bone_pose(j, Transform(Basis(rotations[j]), Vector3.ZERO))


func _build(avatar: Dictionary):
	var names: Array = client.welcome["joint_names"]
	var parents: Array = client.welcome["parents"]
	var rotations: Array = avatar["rotations"]
	var positions: PoolVector3Array = avatar["positions"]
	clear_bones()
	var global_rotations := []
	for j in range(names.size()):
		add_bone(names[j])
		if j == 0:
			global_rotations.append(rotations[0])
			set_bone_rest(0, Transform.IDENTITY)
			continue
		var parent := int(parents[j])
		set_bone_parent(j, parent)
		global_rotations.append(global_rotations[parent] * rotations[j])
		var offset: Vector3 = global_rotations[parent].inverse().xform(positions[j] - positions[parent])
		set_bone_rest(j, Transform(Basis(), offset))
	built = true
	if draw_mannequin:
		var mesh := SphereMesh.new()
		mesh.radius = 0.05
		mesh.height = 0.1
		for joint_name in names:
			var attachment := BoneAttachment.new()
			attachment.bone_name = joint_name
			var ball := MeshInstance.new()
			ball.mesh = mesh
			attachment.add_child(ball)
			add_child(attachment)


func joint_position(joint: int) -> Vector3:
	# where Godot's FK of the streamed rotations puts a joint, in this node's parent's space
	return transform.xform(get_bone_global_pose(joint).origin)
