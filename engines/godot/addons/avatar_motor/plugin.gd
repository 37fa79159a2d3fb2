tool
extends EditorPlugin
# Registers the two node types of the add-on; they also work without the plugin enabled
# (their scripts are plain class_name scripts).


func _enter_tree():
	add_custom_type("AvatarMotorClient", "Node", preload("avatar_motor_client.gd"), null)
	add_custom_type("AvatarMotorSkeleton", "Skeleton", preload("avatar_motor_skeleton.gd"), null)


func _exit_tree():
	remove_custom_type("AvatarMotorClient")
	remove_custom_type("AvatarMotorSkeleton")
