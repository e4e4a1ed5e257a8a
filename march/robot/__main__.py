from march.robot.robot_command import main

main()
